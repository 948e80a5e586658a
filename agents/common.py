"""What every agent process shares: its arguments, the zenoh bus, liveliness, signals, progress.

Topology: with transport.mode "peer" (default) every process of a run listens on its own
loopback port and connects to every other one: a full mesh of zenoh peers, no broker, as V2V
is. Peers do not forward for each other with gossip off, hence the mesh. With transport.mode
"client" every process connects to the zenoh router(s) in transport.connect (`v2vsim router`),
which is how agents on other hosts join a run (README "Across hosts").
Keys: v2vsim/<run>/<kind>/<sender> (v2vsim.comm.transport).

Liveliness: each process declares a token v2vsim/<run>/alive/<role>.<id>; zenoh withdraws it
when the process's session drops, SIGKILL included, which is how the others notice a dead agent
within milliseconds instead of waiting for a timeout.
"""

from __future__ import annotations

import argparse
import dataclasses
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import zenoh

from v2vsim.comm.transport import TransportError, message_key, open_session, parse_key
from v2vsim.config import ConfigError, Scenario, load_scenario

START_TIMEOUT_S = 300.0  # agents import torch and build their models before they are ready


@dataclass(frozen=True)
class AgentArgs:
    scenario: Scenario
    scenario_path: str
    overrides: tuple[str, ...]
    run_id: str
    listen: str  # peer mode: this process's own endpoint
    peers: tuple[str, ...]  # peer mode: every other process's endpoint
    cavs: tuple[str, ...]  # every CAV agent of the run
    egos: tuple[str, ...]  # the fusing CAVs
    cav: str  # this process's CAV id ('' for the driver)
    frames: int
    out: str


def parse_agent_args(role: str, argv: list[str] | None = None) -> AgentArgs:
    p = argparse.ArgumentParser(prog=f"v2vsim-{role}")
    p.add_argument("scenario")
    p.add_argument("--set", dest="overrides", action="append", default=[])
    p.add_argument("--run-id", required=True)
    p.add_argument("--listen", default="", help="peer mode: this process's zenoh endpoint")
    p.add_argument("--peer", dest="peers", action="append", default=[], help="peer mode: another process's endpoint")
    p.add_argument("--cavs", default="", help="comma-separated CAV ids of the run")
    p.add_argument("--egos", default="", help="comma-separated ego CAV ids")
    p.add_argument("--cav", default="")
    p.add_argument("--frames", type=int, default=0)
    p.add_argument("--out", default="")
    a = p.parse_args(argv)
    try:
        sc = load_scenario(a.scenario, a.overrides)
    except ConfigError as e:
        print(f"v2vsim-{role}: error: {e}", file=sys.stderr)
        sys.exit(2)
    split = lambda s: tuple(x for x in s.split(",") if x)  # noqa: E731
    return AgentArgs(scenario=sc, scenario_path=a.scenario, overrides=tuple(a.overrides), run_id=a.run_id,
                     listen=a.listen, peers=tuple(a.peers), cavs=split(a.cavs), egos=split(a.egos), cav=a.cav,
                     frames=a.frames or sc.frames, out=a.out)


def agent_argv(args_scenario: str, overrides: Iterable[str], run_id: str, listen: str, peers: Iterable[str],
               cavs: Iterable[str], egos: Iterable[str], frames: int, cav: str = "", out: str = "") -> list[str]:
    """The command-line tail that `parse_agent_args` reads (the runner builds it)."""
    argv = [args_scenario, "--run-id", run_id, "--cavs", ",".join(cavs), "--egos", ",".join(egos),
            "--frames", str(frames)]
    for o in overrides:
        argv += ["--set", o]
    if listen:
        argv += ["--listen", listen]
    for p in peers:
        argv += ["--peer", p]
    if cav:
        argv += ["--cav", cav]
    if out:
        argv += ["--out", out]
    return argv


class Bus:
    """A zenoh session scoped to one run: put/subscribe by (kind, sender), a queryable, liveliness."""

    def __init__(self, session: zenoh.Session, run_id: str, name: str) -> None:
        self.session = session
        self.run_id = run_id
        self.name = name
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._keep: list[object] = []  # declared entities live as long as the bus
        self._alive: set[str] = set()
        self._ever_alive: set[str] = set()
        self._alive_cond = threading.Condition()
        self._lost_callbacks: list[Callable[[str], None]] = []
        self._keep.append(session.liveliness().declare_subscriber(
            f"v2vsim/{run_id}/alive/*", self._on_liveliness, history=True))

    def ready(self) -> None:
        """Announce this process (models built, subscriptions declared): the driver waits for it."""
        self._keep.append(self.session.liveliness().declare_token(message_key(self.run_id, "alive", self.name)))

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        try:
            _, _, who = parse_key(str(sample.key_expr))
        except ValueError:
            return
        lost = False
        with self._alive_cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(who)
                self._ever_alive.add(who)
            else:
                lost = who in self._alive
                self._alive.discard(who)
            self._alive_cond.notify_all()
        if lost:
            for cb in self._lost_callbacks:
                cb(who)

    def on_lost(self, callback: Callable[[str], None]) -> None:
        self._lost_callbacks.append(callback)

    def is_alive(self, who: str) -> bool:
        with self._alive_cond:
            return who in self._alive

    def was_alive(self, who: str) -> bool:
        with self._alive_cond:
            return who in self._ever_alive

    def wait_alive(self, names: Iterable[str], timeout_s: float) -> None:
        """Block until every named process has joined; TimeoutError names the missing ones."""
        names = set(names)
        deadline = time.monotonic() + timeout_s
        with self._alive_cond:
            while not names <= self._ever_alive:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"agents never joined: {', '.join(sorted(names - self._ever_alive))}")
                self._alive_cond.wait(min(left, 0.5))

    def put(self, kind: str, data: bytes) -> int:
        key = message_key(self.run_id, kind, self.name.split(".")[-1])
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
        pub.put(data)
        return len(data)

    def subscribe(self, kind: str, callback: Callable[[str, bytes], None]) -> None:
        """callback(sender, payload) on zenoh's thread for every message of `kind`; keep it short."""

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                _, _, sender = parse_key(str(sample.key_expr))
            except ValueError:
                return
            callback(sender, sample.payload.to_bytes())

        self._keep.append(self.session.declare_subscriber(f"v2vsim/{self.run_id}/{kind}/*", on_sample))

    def serve(self, kind: str, data: bytes) -> None:
        """Answer queries on v2vsim/<run>/<kind>/<me> with `data` (e.g. the static map)."""
        key = message_key(self.run_id, kind, self.name.split(".")[-1])
        self._keep.append(self.session.declare_queryable(key, lambda q: q.reply(key, data)))

    def fetch(self, kind: str, sender: str, timeout_s: float) -> bytes:
        """Query what another process serves, retrying until it answers or `timeout_s` passes."""
        key = message_key(self.run_id, kind, sender)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for reply in self.session.get(key, timeout=5.0):
                if reply.ok is not None:
                    return reply.ok.payload.to_bytes()
            time.sleep(0.2)
        raise TimeoutError(f"no answer on {key} within {timeout_s:g} s")

    def close(self) -> None:
        for pub in self._pubs.values():
            pub.undeclare()
        for ent in self._keep:
            undeclare = getattr(ent, "undeclare", None)
            if undeclare is not None:
                undeclare()
        self.session.close()


class Stop(Exception):
    """Raised in the main thread on SIGINT/SIGTERM so that `finally` blocks run and files get written."""


def _raise_stop(signum: int, frame: object) -> None:
    raise Stop(signum)


def run_agent(args: AgentArgs, role: str, ident: str, body: Callable[[Bus], int]) -> int:
    """Open the bus, run `body`, and turn every expected failure into a one-line error."""
    signal.signal(signal.SIGTERM, _raise_stop)
    signal.signal(signal.SIGINT, _raise_stop)
    tcfg = args.scenario.transport
    if tcfg.mode == "client":
        tcfg, peers = dataclasses.replace(tcfg, listen=()), ()
    else:
        tcfg, peers = dataclasses.replace(tcfg, listen=(args.listen,) if args.listen else ()), args.peers
    try:
        session = open_session(tcfg, peers=peers)
    except TransportError as e:
        print(f"v2vsim-{role}: error: {e}", file=sys.stderr)
        return 2
    bus = Bus(session, args.run_id, f"{role}.{ident}")
    try:
        return body(bus)
    except Stop as stop:
        return 128 + int(stop.args[0])  # the shell's convention for "ended by signal N"
    except TimeoutError as e:
        print(f"v2vsim-{role} {ident}: error: {e}", file=sys.stderr)
        return 1
    finally:
        bus.close()


def progress_line(who: str, done: int, total: int, t_start: float, every: int = 20) -> None:
    """frames/s and ETA on stderr every `every` frames."""
    if done % every and done != total:
        return
    dt = max(time.monotonic() - t_start, 1e-9)
    fps = done / dt
    eta = (total - done) / fps if fps > 0 else float("inf")
    print(f"[{who}] frame {done}/{total}  {fps:.1f} frames/s  ETA {eta:.0f} s", file=sys.stderr, flush=True)
