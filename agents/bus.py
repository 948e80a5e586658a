"""The zenoh bus of one run, as every agent process uses it (`Bus`): topology, keys, liveliness, control messages.

Topology: with transport.mode "peer" (default) every process of a run listens on its own
loopback port and connects to every other one: a full mesh of zenoh peers, no broker, as V2V
is. Peers do not forward for each other with gossip off, hence the mesh. With transport.mode
"client" every process connects to the zenoh router(s) in transport.connect (`v2vsim router`),
which is how agents on other hosts join a run (docs/cluster.md).
Keys: v2vsim/<run>/<kind>/<sender> (v2vsim.comm.transport).

Liveliness: each process declares a token v2vsim/<run>/alive/<role>.<id>; zenoh withdraws it
when the process's session drops, SIGKILL included, which is how the others notice a dead agent
within milliseconds instead of waiting for a timeout. A process that ends on its own (done,
Ctrl-C, an error) first says `bye` with its exit code, so that a token that drops without a
bye means the process died. Anyone on the bus can declare a token, so under comm.auth a token
alone proves nothing: a process counts as present only once its signed `hello` came (it repeats
one every HEARTBEAT_S), and as gone when its token drops, on its signed bye, or after SILENCE_S
without a hello (a token someone else holds on its key cannot keep a dead process alive).

Control kinds (v2vsim.comm.control: world, done, ack, start, static, vis, scan, bye) are checked by
the Bus itself: only the processes allowed to send a kind are heard, and with comm.auth on
every control message is signed under the run key and verified on receipt. Invalid ones are
dropped and counted (`control_rejections`), with one warning per kind on stderr; so are those a
subscriber refuses (an ack for a frame not published yet, a world outside the window). The V2V data
kinds pass through untouched: the codec signs and checks those. Every kind has a length bound that
is checked before a message is copied off zenoh (ZBytes' length), so a huge message costs no copy.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from typing import Any

import zenoh

from v2vsim.comm.codec import RejectedMessage
from v2vsim.comm.control import (
    CONTROL_KINDS,
    DRIVER,
    ENVELOPE_BYTES,
    MAX_CONTROL_BYTES,
    ControlPolicy,
    ReplayGuard,
    max_payload_bytes,
    open_sealed,
    process_id,
    seal,
)
from v2vsim.comm.signing import Signer
from v2vsim.comm.transport import message_key, parse_key

START_TIMEOUT_S = 300.0  # agents import torch and build their models before they are ready
DRIVER_GRACE_S = 1.0  # after the driver's token drops, how long its `bye` or `done` may still take to arrive
HEARTBEAT_S = 1.0  # under comm.auth every process says a signed hello this often
SILENCE_S = 8.0  # under comm.auth, a process without a hello for this long is gone (its token notwithstanding)


class Bus:
    """A zenoh session scoped to one run: put/subscribe by (kind, sender), a queryable, liveliness.

    key: the comm.auth run key or this process's Identity; control kinds are then signed by put/serve and
    verified by subscribe/fetch. policy: who may send each control kind (None: anyone, the old behaviour).
    """

    def __init__(self, session: zenoh.Session, run_id: str, name: str, *, key: Signer | None = None,
                 policy: ControlPolicy | None = None) -> None:
        self.session = session
        self.run_id = run_id
        self.name = name
        self.key = key
        self.policy = policy
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._keep: list[object] = []  # declared entities live as long as the bus
        self._alive: set[str] = set()
        self._ever_alive: set[str] = set()
        self._alive_cond = threading.Condition()
        self._lost_callbacks: list[Callable[[str], None]] = []
        self._seq: Counter[str] = Counter()
        self._lock = threading.Lock()  # sequence numbers, rejection counts, byes
        self._rejected: Counter[tuple[str, str]] = Counter()
        self._warned: set[str] = set()
        self._byes: dict[str, dict[str, Any]] = {}
        self._last_words: dict[str, Any] = {}  # what say_bye adds to this process's bye (leave_word)
        self._hello_at: dict[str, float] = {}  # process name -> time.monotonic() of its latest signed hello
        self._silent: set[str] = set()  # proven processes whose hellos stopped (gone, token or not)
        self._closing = threading.Event()
        self._threads: list[threading.Thread] = []  # joined by close(): see there
        self._keep.append(session.liveliness().declare_subscriber(
            f"v2vsim/{run_id}/alive/*", self._on_liveliness, history=True))
        self._subscribe("bye", self._on_bye)
        if key is not None:
            self._subscribe("hello", self._on_hello)
            self._start(self._watch_silence, "bus-silence")

    @property
    def authenticated(self) -> bool:
        """Whether control messages are signed and verified (comm.auth on)."""
        return self.key is not None

    def ready(self) -> None:
        """Announce this process (models built, subscriptions declared): the driver waits for it. Under
        comm.auth it also says a signed hello now and every HEARTBEAT_S until the bus closes."""
        self._keep.append(self.session.liveliness().declare_token(message_key(self.run_id, "alive", self.name)))
        if self.key is not None:
            self._start(self._heartbeat, "bus-hello")

    def _start(self, target: Callable[[], None], name: str) -> None:
        thread = threading.Thread(target=target, name=name, daemon=True)
        self._threads.append(thread)
        thread.start()

    def _heartbeat(self) -> None:
        while not self._closing.is_set():
            try:
                self.put("hello", json.dumps({"name": self.name}).encode())
            except Exception:  # the session is closing or failing: the others will notice the silence
                return
            self._closing.wait(HEARTBEAT_S)

    def _proven(self, who: str) -> bool:
        """Under comm.auth, whether `who` said a signed hello (without, a token is all there is). Under the lock."""
        return self.key is None or who in self._hello_at

    def _on_hello(self, name: str, payload: bytes) -> None:
        with self._alive_cond:
            first = name not in self._hello_at
            self._hello_at[name] = time.monotonic()
            self._silent.discard(name)
            if first and name in self._alive:
                self._ever_alive.add(name)
            self._alive_cond.notify_all()

    def _watch_silence(self) -> None:
        while not self._closing.wait(0.25):
            now = time.monotonic()
            with self._alive_cond:
                quiet = [n for n, t in self._hello_at.items()
                         if now - t > SILENCE_S and n not in self._silent and n != self.name]
                self._silent.update(quiet)
                lost = [n for n in quiet if n in self._alive]
                if quiet:
                    self._alive_cond.notify_all()
            for who in lost:
                for cb in self._lost_callbacks:
                    cb(who)

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        try:
            _, _, who = parse_key(str(sample.key_expr))
        except ValueError:
            return
        lost = False
        with self._alive_cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(who)
                if self._proven(who):
                    self._ever_alive.add(who)
            else:
                lost = who in self._alive and who in self._ever_alive and who not in self._silent
                self._alive.discard(who)
            self._alive_cond.notify_all()
        if lost:
            for cb in self._lost_callbacks:
                cb(who)

    def on_lost(self, callback: Callable[[str], None]) -> None:
        self._lost_callbacks.append(callback)

    def is_alive(self, who: str) -> bool:
        """Its token is up and, under comm.auth, it proved itself and has not gone silent."""
        with self._alive_cond:
            return who in self._alive and self._proven(who) and who not in self._silent

    def was_alive(self, who: str) -> bool:
        with self._alive_cond:
            return who in self._ever_alive

    def wait_alive(self, names: Iterable[str], timeout_s: float) -> None:
        """Block until every named process has joined (under comm.auth: token and signed hello); TimeoutError
        names the missing ones."""
        names = set(names)
        deadline = time.monotonic() + timeout_s
        with self._alive_cond:
            while not names <= self._ever_alive:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"agents never joined: {', '.join(sorted(names - self._ever_alive))}")
                self._alive_cond.wait(min(left, 0.5))

    # ---- control messages: signing, verification, counting ----------------------------------

    def _seal(self, kind: str, data: bytes) -> bytes:
        if kind not in CONTROL_KINDS or self.key is None:
            return data
        with self._lock:
            seq = self._seq[kind]
            self._seq[kind] += 1
        return seal(self.key, self.run_id, kind, self.name, seq, data)

    def _open(self, kind: str, sender: str, data: bytes, guard: ReplayGuard | None) -> tuple[str, bytes] | None:
        """(process name, payload) of a message that arrived under key sender `sender`, or None (counted).

        The process name is verified under comm.auth; without it, it is only the key's sender chunk."""
        if kind not in CONTROL_KINDS:
            return sender, data
        try:
            if self.key is None:
                if self.policy is not None and not self.policy.allows_key_sender(kind, sender):
                    raise RejectedMessage("unknown_sender", f"{kind} from {sender!r}")
                return sender, data
            opened = open_sealed(self.key, self.run_id, kind, sender, data, self.policy)
            if guard is not None:
                guard.check(kind, opened)
            return opened.sender, opened.payload
        except RejectedMessage as e:
            self._reject(kind, sender, e)
            return None

    def _reject(self, kind: str, sender: str, e: RejectedMessage) -> None:
        with self._lock:
            self._rejected[(kind, e.reason)] += 1
            first = kind not in self._warned
            self._warned.add(kind)
        if first:
            print(f"v2vsim-{self.name}: dropped a {kind!r} control message under sender {sender!r} ({e}); "
                  f"further invalid {kind!r} messages are only counted", file=sys.stderr, flush=True)

    def control_rejections(self) -> dict[tuple[str, str], int]:
        """(kind, reason) -> how many invalid control messages were dropped so far."""
        with self._lock:
            return dict(self._rejected)

    def _on_bye(self, name: str, payload: bytes) -> None:
        try:
            doc = json.loads(payload)
            if not isinstance(doc, dict):
                return
        except ValueError:
            return
        if self.key is None:  # `name` is only the key's sender chunk: take the name the payload gives
            claimed = str(doc.get("name", ""))
            if process_id(claimed) != name or (self.policy is not None and not self.policy.allows("bye", claimed)):
                return
            name = claimed
        with self._lock:
            self._byes[name] = doc
        with self._alive_cond:
            self._alive_cond.notify_all()

    def farewell(self, who: str) -> dict[str, Any] | None:
        """What process `who` said when it ended on its own ({'name', 'code', 'why'}), None if it did not."""
        with self._lock:
            return self._byes.get(who)

    def driver_gone(self) -> bool:
        """The driver joined and its liveliness token has dropped (ended or died)."""
        return self.was_alive(DRIVER) and not self.is_alive(DRIVER)

    def leave_word(self, **doc: Any) -> None:
        """Fields this process's bye will carry beside its name, code and reason (the driver's SSM conflicts and
        refusals, for egos that stop before its `done`); the whole bye stays within MAX_CONTROL_BYTES."""
        self._last_words.update(doc)

    def say_bye(self, code: int, why: str = "") -> None:
        """Tell the run this process ends on its own (best effort: the session may be failing)."""
        doc = {"name": self.name, "code": int(code), "why": why[:200]}
        payload = json.dumps({**self._last_words, **doc}).encode()
        if len(payload) > MAX_CONTROL_BYTES - ENVELOPE_BYTES:  # too long to be taken: the plain bye instead
            payload = json.dumps(doc).encode()
        try:
            self.put("bye", payload)
        except Exception:  # a bye that cannot be sent is a death the others will notice
            pass

    # ---- pub/sub ---------------------------------------------------------------------------

    def put(self, kind: str, data: bytes) -> int:
        """Publish on v2vsim/<run>/<kind>/<me> (control kinds signed under comm.auth); bytes sent."""
        key = message_key(self.run_id, kind, process_id(self.name))
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
        data = self._seal(kind, data)
        pub.put(data)
        return len(data)

    def subscribe(self, kind: str, callback: Callable[[str, bytes], None], *, max_bytes: int | None = None,
                  oversize: Callable[[str], None] | None = None) -> None:
        """callback(sender, payload) on zenoh's thread for every valid message of `kind`; keep it short.

        Control kinds arrive verified and unwrapped; invalid ones never reach the callback. The callback refuses
        a control message by raising RejectedMessage (e.g. an ack for a frame not published yet): counted like
        the Bus's own refusals. A message longer than `max_bytes` (a control kind's payload: at most
        max_payload_bytes(kind)) is refused from its length alone, before it is copied off the transport, so a
        huge one costs no copy: a control kind's is counted (size_mismatch), a data kind's reported to
        `oversize(sender)` (the receiver counts its own kinds)."""
        self._subscribe(kind, callback, by_name=False, max_bytes=max_bytes, oversize=oversize)

    def _limit(self, kind: str, max_bytes: int | None) -> int | None:
        """The longest message of `kind` kept off the transport: a control kind's payload bound plus its envelope."""
        if kind not in CONTROL_KINDS:
            return max_bytes
        payload = max_bytes if max_bytes is not None else max_payload_bytes(kind)
        return None if payload is None else payload + (ENVELOPE_BYTES if self.key is not None else 0)

    def _too_long(self, kind: str, sender: str, payload: zenoh.ZBytes, limit: int | None,
                  oversize: Callable[[str], None] | None = None) -> bool:
        """Whether a message is over `limit` (then refused and counted); only its length is read."""
        n = len(payload)
        if limit is None or n <= limit:
            return False
        if kind in CONTROL_KINDS:
            self._reject(kind, sender, RejectedMessage("size_mismatch", f"{n} bytes, at most {limit}"))
        elif oversize is not None:
            oversize(sender)
        return True

    def _subscribe(self, kind: str, callback: Callable[[str, bytes], None], by_name: bool = True,
                   max_bytes: int | None = None, oversize: Callable[[str], None] | None = None) -> None:
        """subscribe(), with callback(process name, payload) when by_name (see `_open`)."""
        guard = ReplayGuard()
        limit = self._limit(kind, max_bytes)

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                _, _, sender = parse_key(str(sample.key_expr))
            except ValueError:
                return
            if self._too_long(kind, sender, sample.payload, limit, oversize):
                return
            opened = self._open(kind, sender, sample.payload.to_bytes(), guard)
            if opened is None:
                return
            try:
                callback(opened[0] if by_name else sender, opened[1])
            except RejectedMessage as e:
                self._reject(kind, sender, e)

        # run on zenoh's own thread (indirect=False), not queued for a Python thread: zenoh-python's default queue
        # has no bound, so a flood faster than the callbacks grew it without limit (+290 to +400 MiB for 100
        # worlds of 8 MiB when each callback took 10 ms); called directly, a slow receiver slows the sender down
        self._keep.append(self.session.declare_subscriber(f"v2vsim/{self.run_id}/{kind}/*",
                                                          zenoh.handlers.Callback(on_sample, indirect=False)))

    def serve(self, kind: str, data: bytes) -> None:
        """Answer queries on v2vsim/<run>/<kind>/<me> with `data` (e.g. the static map)."""
        key = message_key(self.run_id, kind, process_id(self.name))
        sealed = self._seal(kind, data)
        self._keep.append(self.session.declare_queryable(key, lambda q: q.reply(key, sealed)))

    def fetch(self, kind: str, sender: str, timeout_s: float) -> bytes:
        """Query what another process serves, retrying until a valid answer comes or `timeout_s` passes."""
        key = message_key(self.run_id, kind, sender)
        limit = self._limit(kind, None)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            # every queryable's reply, not zenoh's pick of one: an impostor's must not hide the real one
            for reply in self.session.get(key, target=zenoh.QueryTarget.ALL,
                                          consolidation=zenoh.ConsolidationMode.NONE, timeout=5.0):
                if reply.ok is not None and not self._too_long(kind, sender, reply.ok.payload, limit):
                    opened = self._open(kind, sender, reply.ok.payload.to_bytes(), None)
                    if opened is not None:
                        return opened[1]
            time.sleep(0.2)
        raise TimeoutError(f"no answer on {key} within {timeout_s:g} s")

    def close(self) -> None:
        """Stop the bus's threads, undeclare everything and close the session; return once the threads ended.

        A thread still inside a zenoh call when the interpreter finalises is ended by pthread_exit on its way
        back to the GIL, and that forced unwind through zenoh's Rust frames aborts the process after its work
        is done ("FATAL: exception not rethrown", SIGABRT). A put can block for a while (congestion control
        BLOCK towards a peer that was just killed), so a thread that does not end at once is joined again after
        the session closed, which makes its put return."""
        self._closing.set()
        for thread in self._threads:
            thread.join(timeout=1.0)  # each wakes at once on _closing unless it is inside a put
        for ent in [*self._pubs.values(), *self._keep]:
            undeclare = getattr(ent, "undeclare", None)
            if undeclare is not None:
                try:
                    undeclare()
                except RuntimeError:  # "Already borrowed": a thread is still putting on it; close() ends that
                    pass
        self.session.close()
        for thread in self._threads:
            thread.join(timeout=10.0)
