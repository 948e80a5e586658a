"""zenoh plumbing: session config, clear errors, key expressions, and thin byte pub/sub.

What zenoh 1.10 does here (checked on this machine):
  * A listen endpoint whose port is taken fails zenoh.open at once with ZError
    "... Address already in use (os error 98) ...".
  * client mode with an unreachable connect endpoint fails zenoh.open at once with ZError
    "Unable to connect to any of [...]"; with connect/timeout_ms and exit_on_failure it
    keeps retrying until the timeout and then fails ("... Timeout!").
  * peer mode with an unreachable connect endpoint opens anyway (after ~0.5 s) and keeps
    retrying in the background, unless exit_on_failure is set: then every endpoint without
    its own "#exit_on_failure=false" must connect within the timeout.
  * Peers do not forward between other peers (routing "peer_to_peer"): with gossip off, two
    agents exchange data only over a direct link or through a router.
  * A message far longer than transport/link/rx/max_message_size is dropped by the receiver's zenoh before
    it is reassembled (no copy of it in that process), and the link and later messages go on. Only those
    over ~16 MiB reliably: of 20 messages of 8 MiB under a 1.2 MB bound, 18 were delivered.
So `open_session` makes the user's transport.connect endpoints (a router, usually) required,
with a timeout, and the `peers` endpoints (other agents, which may start later) optional and
retried; both failure modes come back as a one-line TransportError for the CLI to print
before exiting with code 2.

Key expressions: v2vsim/<run_id>/<kind>/<sender_id>.
"""

from __future__ import annotations

import contextlib
import json
import queue
import re
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import zenoh

from v2vsim.config import TransportConfig

KEY_ROOT = "v2vsim"
_BAD_CHUNK = re.compile(r"[/*$?#]")
DEFAULT_CONNECT_TIMEOUT_MS = 5000


class TransportError(Exception):
    """A transport problem a user can fix (port in use, router unreachable); one line of text."""


# ---- key expressions -------------------------------------------------------------------------


def _chunk(value: str, what: str) -> str:
    if not value or _BAD_CHUNK.search(value) or value.startswith("@"):
        raise ValueError(f"{what} {value!r} cannot be a zenoh key chunk (non-empty, no / * $ ? #, no leading @)")
    return value


def message_key(run_id: str, kind: str, sender_id: str) -> str:
    """The key one sender publishes one kind of message on."""
    return f"{KEY_ROOT}/{_chunk(run_id, 'run id')}/{_chunk(kind, 'kind')}/{_chunk(sender_id, 'sender id')}"


def subscription_key(run_id: str, kind: str | None = None) -> str:
    """Every sender's messages of one kind, or (kind None) everything of the run."""
    if kind is None:
        return f"{KEY_ROOT}/{_chunk(run_id, 'run id')}/**"
    return f"{KEY_ROOT}/{_chunk(run_id, 'run id')}/{_chunk(kind, 'kind')}/*"


def parse_key(key: str) -> tuple[str, str, str]:
    """v2vsim/<run>/<kind>/<sender> -> (run, kind, sender); ValueError for anything else."""
    parts = key.split("/")
    if len(parts) != 4 or parts[0] != KEY_ROOT or not all(parts[1:]):
        raise ValueError(f"not a v2vsim message key: {key!r}")
    return parts[1], parts[2], parts[3]


# ---- config and session ----------------------------------------------------------------------


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (another process can still take it: retry on error)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def free_ports(n: int, host: str = "127.0.0.1") -> list[int]:
    """`n` distinct TCP ports that were free a moment ago: every socket stays bound until all are
    picked, so one plan never holds the same port twice (another process can still take one before
    its user binds it: the runner re-plans when that happens)."""
    with contextlib.ExitStack() as stack:
        socks = [stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) for _ in range(n)]
        for s in socks:
            s.bind((host, 0))
        return [int(s.getsockname()[1]) for s in socks]


def loopback_endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def _optional(endpoint: str) -> str:
    """Mark an endpoint as not required (zenoh per-endpoint config after '#')."""
    if "exit_on_failure" in endpoint:
        return endpoint
    return endpoint + (";" if "#" in endpoint else "#") + "exit_on_failure=false"


def zenoh_config(transport_cfg: TransportConfig, listen_port: int | None = None, *,
                 peers: Sequence[str] = (), connect_timeout_ms: int = DEFAULT_CONNECT_TIMEOUT_MS,
                 max_message_bytes: int | None = None) -> zenoh.Config:
    """A zenoh config with multicast scouting and gossip off and only explicit endpoints.

    listen: transport.listen if given, else tcp/127.0.0.1:<listen_port>, else (peer mode) an
        ephemeral loopback port; clients do not listen.
    connect: transport.connect endpoints are required (open fails after connect_timeout_ms);
        `peers` (other agents' listen endpoints) are optional and retried every 0.1-1 s.
    max_message_bytes: zenoh's own bound on a message it reassembles from fragments
        (transport/link/rx/max_message_size, default 1 GiB): a longer one is dropped by zenoh, uncounted,
        before it takes memory beyond the bound; the link stays up (zenoh 1.10: reliably only for messages
        over ~16 MiB, so receivers still check lengths themselves).
    """
    if transport_cfg.mode == "client" and not transport_cfg.connect:
        raise TransportError("transport.mode is 'client' but transport.connect names no router endpoint")
    if transport_cfg.listen:
        listen = list(transport_cfg.listen)
    elif listen_port is not None:
        listen = [loopback_endpoint(listen_port)]
    elif transport_cfg.mode == "peer":
        listen = ["tcp/127.0.0.1:0"]
    else:
        listen = []
    connect = list(transport_cfg.connect) + [_optional(p) for p in peers]
    settings: dict[str, object] = {
        "mode": transport_cfg.mode,
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": False,
        "listen/endpoints": listen,
        "connect/endpoints": connect,
        "connect/timeout_ms": int(connect_timeout_ms),
        "connect/exit_on_failure": bool(transport_cfg.connect),
        "connect/retry": {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2},
        "listen/exit_on_failure": True,
        "adminspace/enabled": False,
    }
    if max_message_bytes is not None:
        settings["transport/link/rx/max_message_size"] = int(max_message_bytes)
    cfg = zenoh.Config()
    for path, value in settings.items():
        try:
            cfg.insert_json5(path, json.dumps(value))
        except zenoh.ZError as e:
            raise TransportError(f"zenoh config {path}={json.dumps(value)}: {_first_line(e)}") from None
    return cfg


def _first_line(e: BaseException) -> str:
    """zenoh's message without the Rust source location and on one line."""
    text = " ".join(str(e).split())
    text = re.sub(r" at /\S+\.rs:\d+\.?", "", text)
    m = re.search(r'msg: "(.*?)"', text)  # json5 errors wrap the useful part in a Rust debug print
    return (m.group(1) if m else text).strip()


def _explain(e: BaseException, cfg_listen: Sequence[str], cfg_connect: Sequence[str], timeout_ms: int) -> str:
    text = _first_line(e)
    if "Address already in use" in text or "os error 98" in text:
        m = re.search(r"bound to (\S+?):\s", text)
        where = m.group(1) if m else ", ".join(cfg_listen)
        return f"zenoh: cannot listen on {where}: address already in use (pick another port in transport.listen)"
    if "Unable to connect" in text:
        timed = "Timeout" in text
        return (f"zenoh: cannot reach {', '.join(cfg_connect) or 'any endpoint'}"
                f"{f' within {timeout_ms / 1000:g} s' if timed else ''} (is the zenoh router running? "
                "check transport.connect)")
    return f"zenoh: could not open a session: {text}"


def open_session(transport_cfg: TransportConfig, listen_port: int | None = None, *,
                 peers: Sequence[str] = (), connect_timeout_ms: int = DEFAULT_CONNECT_TIMEOUT_MS,
                 max_message_bytes: int | None = None) -> zenoh.Session:
    """Open a zenoh session per `zenoh_config`; every failure becomes a one-line TransportError."""
    cfg = zenoh_config(transport_cfg, listen_port, peers=peers, connect_timeout_ms=connect_timeout_ms,
                       max_message_bytes=max_message_bytes)
    listen = list(transport_cfg.listen) or ([loopback_endpoint(listen_port)] if listen_port is not None else [])
    try:
        return zenoh.open(cfg)
    except Exception as e:  # zenoh raises ZError; anything else is just as fatal to the agent
        raise TransportError(_explain(e, listen, transport_cfg.connect, connect_timeout_ms)) from None


# ---- byte pub/sub ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Received:
    """One sample as it came off zenoh. recv_wall is time.monotonic() (meaningful in realtime)."""

    key: str
    data: bytes = field(repr=False)
    recv_wall: float


class Publisher:
    """Publishes bytes reliably (the channel model, not zenoh, decides about loss)."""

    def __init__(self, session: zenoh.Session, key: str, *, express: bool = True) -> None:
        self.key = key
        self._pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                              reliability=zenoh.Reliability.RELIABLE, express=express)

    def put(self, data: bytes) -> int:
        """Send; returns the number of bytes handed to zenoh (for CommStats)."""
        self._pub.put(data)
        return len(data)

    def matched(self) -> bool:
        """Whether any subscriber is currently reachable for this key."""
        return bool(self._pub.matching_status.matching)

    def wait_matched(self, timeout_s: float, poll_s: float = 0.01) -> bool:
        """Block until a subscriber matches (routes form asynchronously after open)."""
        deadline = time.monotonic() + timeout_s
        while not self.matched():
            if time.monotonic() >= deadline:
                return False
            time.sleep(poll_s)
        return True

    def close(self) -> None:
        self._pub.undeclare()


class Subscriber:
    """Puts every sample on `queue` as a `Received`; the consumer thread decides what to do.

    With maxsize > 0 and a full queue the sample is counted in `overflow` and dropped (the
    zenoh callback thread must never block). With max_bytes, a longer sample is counted in
    `oversize` and dropped from its length alone, before it is copied off zenoh's buffer.
    """

    def __init__(self, session: zenoh.Session, key_expr: str, *, maxsize: int = 0, max_bytes: int | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.key_expr = key_expr
        self.queue: queue.Queue[Received] = queue.Queue(maxsize)
        self.overflow = 0
        self.oversize = 0
        self.max_bytes = max_bytes
        self._clock = clock
        self._sub = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if self.max_bytes is not None and len(sample.payload) > self.max_bytes:
            self.oversize += 1
            return
        try:
            self.queue.put_nowait(Received(str(sample.key_expr), sample.payload.to_bytes(), self._clock()))
        except queue.Full:
            self.overflow += 1

    def get(self, timeout: float | None = None) -> Received | None:
        """The next sample, or None after `timeout` seconds (None = wait forever)."""
        try:
            return self.queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def close(self) -> None:
        self._sub.undeclare()
