"""`v2vsim run`: start the simulator driver, one perception agent per CAV and the ego fusion
process(es), watch them, and stop them all cleanly on Ctrl-C.

Results are written by the ego process (metrics.json, report.md, plots, recording.rrd) when it
finishes, is interrupted, or carries on without lost agents. The runner only orchestrates:
a CAV that dies is the ego's business (it fuses the others); a driver or ego that dies ends
the run with an error.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import re
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

from agents.common import agent_argv
from v2vsim.comm.transport import TransportError, free_port, loopback_endpoint, open_session
from v2vsim.config import Scenario
from v2vsim.perception import check_scenario
from v2vsim.sensing import ego_ids
from v2vsim.traffic.base import cav_id

STOP_GRACE_S = 5.0  # after SIGINT, children get this long to write their files before SIGKILL


@dataclasses.dataclass
class Child:
    name: str
    proc: subprocess.Popen


def _check_listen(endpoints: tuple[str, ...]) -> None:
    """Fail early, in one line, when a listen endpoint's port is taken."""
    for ep in endpoints:
        m = re.fullmatch(r"tcp/(\[?[^\]]+\]?|[^:]+):(\d+)", ep.split("#")[0])
        if not m:
            raise TransportError(f"transport.listen: {ep!r} is not a tcp/HOST:PORT endpoint")
        host, port = m.group(1).strip("[]"), int(m.group(2))
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        with socket.socket(family, socket.SOCK_STREAM) as s:
            try:
                s.bind((host, port))
            except OSError as e:
                raise TransportError(f"zenoh: cannot listen on {ep}: {e.strerror.lower()} "
                                     "(pick another port in transport.listen)") from None


def plan_endpoints(sc: Scenario, names: list[str]) -> dict[str, str]:
    """Peer mode: one listen endpoint per process (the driver takes transport.listen if set)."""
    if sc.transport.mode == "client":
        return {n: "" for n in names}
    out = {n: loopback_endpoint(free_port()) for n in names}
    if sc.transport.listen:
        out[names[0]] = sc.transport.listen[0]
    return out


def run(sc: Scenario, out: Path, frames: int | None = None, remote_cavs: tuple[str, ...] = (),
        run_id: str | None = None) -> int:
    frames = frames or sc.frames
    run_id = run_id or uuid.uuid4().hex[:8]
    cavs = [cav_id(i) for i in range(sc.cavs.count)]
    egos = ego_ids(sc, cavs)
    check_scenario(sc)
    out.mkdir(parents=True, exist_ok=True)
    try:
        if sc.transport.mode == "client":  # the router(s) must be reachable before anything starts
            open_session(dataclasses.replace(sc.transport, listen=())).close()
        else:
            _check_listen(sc.transport.listen)
    except TransportError as e:
        print(f"v2vsim: error: {e}", file=sys.stderr)
        return 2
    procs = ["driver.main"] + [f"cav.{c}" for c in cavs if c not in remote_cavs] + [f"ego.{e}" for e in egos]
    endpoints = plan_endpoints(sc, procs)
    overrides = _overrides_for_children(sc)
    print(f"v2vsim: run {run_id}: {len(cavs)} CAVs, ego {', '.join(egos)}, {frames} frames, "
          f"methods {', '.join(sc.perception.methods)} -> {out}", file=sys.stderr)
    if remote_cavs:
        print("v2vsim: waiting for remote CAVs; on their hosts run:", file=sys.stderr)
        for c in remote_cavs:
            print(f"  v2vsim agent {sc.source} --cav {c} --run-id {run_id} --cavs {','.join(cavs)} "
                  f"--egos {','.join(egos)} --frames {frames} " + " ".join(f"--set {o}" for o in overrides),
                  file=sys.stderr)
    children: list[Child] = []
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for name in procs:
        role, ident = name.split(".", 1)
        module = {"driver": "agents.driver", "cav": "agents.cav", "ego": "agents.ego"}[role]
        argv = agent_argv(sc.source, overrides, run_id, endpoints[name],
                          [ep for n, ep in endpoints.items() if n != name and ep], cavs, egos, frames,
                          cav="" if role == "driver" else ident, out=str(out))
        proc = subprocess.Popen([sys.executable, "-m", module, *argv], env=env, stdin=subprocess.DEVNULL)
        children.append(Child(name, proc))
    interrupted = False
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        code = _watch(children)
    except KeyboardInterrupt:
        interrupted = True
        code = 130
        print("v2vsim: interrupted; stopping every process (partial results are written)", file=sys.stderr)
    finally:
        _stop_all(children)
        signal.signal(signal.SIGTERM, previous)
    if not interrupted and code == 0:
        print(f"v2vsim: done: {out / 'report.md'}", file=sys.stderr)
    return code


def _overrides_for_children(sc: Scenario) -> list[str]:
    """Children re-read the scenario file; command-line overrides travel with them."""
    return list(sc.overrides)


def _watch(children: list[Child]) -> int:
    """Wait for the egos to finish; fail fast when the driver or an ego fails."""
    while True:
        egos = [c for c in children if c.name.startswith("ego.")]
        driver = next(c for c in children if c.name == "driver.main")
        rc = driver.proc.poll()
        if rc not in (None, 0):
            print(f"v2vsim: error: the simulator driver exited with code {rc}", file=sys.stderr)
            return 2 if rc == 2 else 1
        codes = [e.proc.poll() for e in egos]
        failed = [(e.name, c) for e, c in zip(egos, codes, strict=True) if c not in (None, 0)]
        if failed:
            name, c = failed[0]
            print(f"v2vsim: error: {name} exited with code {c}", file=sys.stderr)
            return 2 if c == 2 else 1
        if all(c == 0 for c in codes):
            return 0
        for c in children:
            rc = c.proc.poll()
            # A CAV killed by a signal is a dead agent the ego copes with; one that exits with an
            # error is a failure to report (it would otherwise leave the driver waiting for it).
            if c.name.startswith("cav.") and rc is not None and 0 < rc < 128:
                print(f"v2vsim: error: {c.name} exited with code {rc}", file=sys.stderr)
                return 2 if rc == 2 else 1
        time.sleep(0.2)


def _stop_all(children: list[Child]) -> None:
    """SIGINT to every child still running, then SIGKILL after STOP_GRACE_S: no orphans."""
    for c in children:
        if c.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                c.proc.send_signal(signal.SIGINT)
    deadline = time.monotonic() + STOP_GRACE_S
    for c in children:
        left = max(0.0, deadline - time.monotonic())
        try:
            c.proc.wait(timeout=left)
        except subprocess.TimeoutExpired:
            c.proc.kill()
            c.proc.wait()
