"""`v2vsim run`: start the simulator driver, one perception agent per CAV and the ego fusion
process(es), watch them, show one progress line for the run, and stop them all cleanly on Ctrl-C.

Results are written by the ego process (metrics.json, report.md, plots, recording.rrd) when it
finishes, is interrupted, or carries on without lost agents. The runner only orchestrates:
a CAV that dies is the ego's business (it fuses the others); a driver or ego that dies ends
the run with an error.

Children: each runs in its own process group (a terminal's Ctrl-C reaches the runner only, which
stops them in order) and gets SIGTERM when the runner dies (PR_SET_PDEATHSIG cold; forked by the warm
starter, the starter stops them when the runner's connection closes: v2vsim.launch), so a SIGKILLed
runner leaves no orphans. Their stderr comes through the runner: progress records feed
the one display (agents/progress.py), every other line is passed on as it is.

Ports (peer mode): the runner picks one free loopback port per process; a child binds it seconds
later, after importing torch, and another program may take it meanwhile. A child that cannot
listen on a port the runner picked is a race, not a user error: the runner picks new ports and
restarts every process (PORT_ATTEMPTS in all). The user's own transport.listen stays a clean exit 2.
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
import threading
import time
import uuid
from pathlib import Path

from agents.args import agent_argv
from agents.progress import ENV as PROGRESS_ENV
from agents.progress import ProgressDisplay, parse_record
from agents.timing import LAUNCHED_ENV
from v2vsim.comm.identity import Identity, new_run_instance, write_identity_file
from v2vsim.comm.identity import issue as issue_identities
from v2vsim.comm.misbehaviour import describe
from v2vsim.comm.transport import TransportError, free_ports, loopback_endpoint, open_session
from v2vsim.config import ConfigError, Scenario, check_output_dir
from v2vsim.evaluation.fleet_report import merge_fleet
from v2vsim.evaluation.status import cav_ranges, terminal_line
from v2vsim.launch import Launcher, Process, launcher
from v2vsim.perception.build import method_checkpoints
from v2vsim.perception.checks import check_scenario
from v2vsim.perception.fleet import fleet_types
from v2vsim.run_outcome import ego_statuses, write_failure_metrics
from v2vsim.sensors.sensing import ego_ids
from v2vsim.traffic.penetration import connected_cavs

STOP_GRACE_S = 5.0  # after SIGINT, children get this long to write their files before SIGKILL
EGO_NOTICE_S = 3.0  # after the driver dies mid-run, the egos get this long to notice it and say so themselves
PORT_ATTEMPTS = 3  # plans of ports tried when another program takes a port the runner picked
PORT_RACE_EXIT = 75  # EX_TEMPFAIL: an agent may exit with it when it cannot listen on its --listen port


class PortRace(Exception):
    """A child could not listen on a port the runner picked for it: another program took it."""

    def __init__(self, child: str, endpoint: str) -> None:
        super().__init__(f"{child} could not listen on {endpoint}")
        self.child = child
        self.endpoint = endpoint


@dataclasses.dataclass
class Child:
    name: str
    proc: Process  # subprocess.Popen, or forked by the warm starter (v2vsim.launch)
    endpoint: str = ""  # its listen endpoint ("" in client mode)
    picked: bool = False  # the runner picked `endpoint` (not the user's transport.listen)
    port_taken: bool = False  # it said its listen address is in use
    quiet: bool = False  # being killed for a restart: its output is of no interest
    reader: threading.Thread | None = None

    def exited(self) -> int | None:
        """Its exit code once it has exited and its last stderr lines (the reason) are through."""
        rc = self.proc.poll()
        if rc is not None and self.reader is not None:
            self.reader.join(timeout=2.0)
        return rc


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
                raise TransportError(f"zenoh: cannot listen on {ep}: {(e.strerror or str(e)).lower()} "
                                     "(pick another port in transport.listen)") from None


def plan_endpoints(sc: Scenario, names: list[str]) -> dict[str, str]:
    """Peer mode: one listen endpoint per process, all distinct (the driver takes transport.listen if set)."""
    if sc.transport.mode == "client":
        return {n: "" for n in names}
    out = {n: loopback_endpoint(p) for n, p in zip(names, free_ports(len(names)), strict=True)}
    if sc.transport.listen:
        out[names[0]] = sc.transport.listen[0]
    return out


def run(sc: Scenario, out: Path, frames: int | None = None, remote_cavs: tuple[str, ...] = (),
        run_id: str | None = None) -> int:
    """Run the co-simulation; the exit code for `v2vsim run` (ConfigError for a bad --frames, --out or
    --remote-cavs; 0 for a degraded run too: its files are written and its status says what happened)."""
    if frames is not None and frames < 1:
        raise ConfigError(f"--frames {frames}: expected a number of frames >= 1")
    frames = frames or sc.frames
    run_id = run_id or uuid.uuid4().hex[:8]
    cavs = connected_cavs(sc)  # every placed vehicle, unless cavs.penetration leaves some unconnected
    egos = ego_ids(sc, cavs)
    unknown = [c for c in remote_cavs if c not in cavs]
    if unknown:  # it would print an agent command that cannot join and run every CAV here
        raise ConfigError(f"--remote-cavs {','.join(remote_cavs)}: {', '.join(unknown)}: not a CAV of this run "
                          f"(cavs.count {sc.cavs.count}: {cav_ranges(cavs)})")
    if remote_cavs and sc.transport.mode != "client":  # peers do not relay: an agent elsewhere could never join
        raise ConfigError(f"--remote-cavs {','.join(remote_cavs)}: remote agents join through a zenoh router, and "
                          f"this run is in transport.mode {sc.transport.mode}: start `v2vsim router` and add --set "
                          "transport.mode=client --set 'transport.connect=[tcp/ROUTER_HOST:7447]' (docs/cluster.md)")
    with launcher() as launch:  # a warm starter (v2vsim.launch) imports while the scenario is checked
        return _run(sc, out, frames, run_id, remote_cavs, cavs, egos, launch)


def _run(sc: Scenario, out: Path, frames: int, run_id: str, remote_cavs: tuple[str, ...], cavs: list[str],
         egos: list[str], launch: Launcher) -> int:
    """`run` once its arguments are checked: check the scenario, start every process through `launch`, watch
    them, stop them, and say how the run ended."""
    plan = check_scenario(sc)  # the scenario's models, resolved once (v2vsim.perception.plan), and checked
    check_output_dir(out, "--out")
    try:
        if sc.transport.mode == "client":  # the router(s) must be reachable before anything starts
            open_session(dataclasses.replace(sc.transport, listen=())).close()
        else:
            _check_listen(sc.transport.listen)
    except TransportError as e:
        print(f"v2vsim: error: {e}", file=sys.stderr)
        return 2
    procs = ["driver.main"] + [f"cav.{c}" for c in cavs if c not in remote_cavs] + [f"ego.{e}" for e in egos]
    overrides = _overrides_for_children(sc)
    runnable = plan.methods
    for lie in sc.misbehaviour:
        print(f"v2vsim: ATTACKED RUN (misbehaviour): {describe(lie)}", file=sys.stderr)
    if sc.cavs.penetration is not None:
        print(f"v2vsim: penetration {sc.cavs.penetration:g}: connected {', '.join(cavs)} of {sc.cavs.count} placed "
              "vehicles (the others are driven by SUMO and send nothing)", file=sys.stderr)
    print(f"v2vsim: run {run_id}: {len(cavs)} CAVs, ego {', '.join(egos)}, {frames} frames, "
          f"methods {', '.join(runnable)} -> {out}", file=sys.stderr)
    dropped = [m for m in sc.perception.methods if m not in runnable]
    if dropped:
        why = (f"this run's modality is {sc.perception.modality}" if sc.perception.modality != "lidar"
               else "an ego of this mixed fleet carries no LiDAR")
        print(f"v2vsim: note: {', '.join(dropped)} left out: early fusion ships LiDAR points and {why}",
              file=sys.stderr)
    if sc.cavs.fleet:
        types = fleet_types(sc, cavs)
        print("v2vsim: fleet: " + ", ".join(f"{c} {t.label}" for c, t in types.items()), file=sys.stderr)
    z = plan.zoo
    untrained = [m for m, f in method_checkpoints(plan, runnable).items() if f is None] if z is not None else []
    if untrained:  # (the whole run untrained, weights none or no zoo: the report's first lines say so)
        print(f"v2vsim: note: {', '.join(untrained)}: no checkpoint in the zoo at {z.root} (perception.weights: "
              f"{sc.perception.weights}): run{'s' if len(untrained) == 1 else ''} untrained, with seeded random "
              "weights; report.md and metrics.json (checkpoints: null) say so", file=sys.stderr)
    # comm.auth.identity per_process: the runner is the run's authority (v2vsim/comm/identity.py)
    identities = issue_identities(run_id, ["driver.main", *(f"cav.{c}" for c in cavs), *(f"ego.{e}" for e in egos)]
                                  ) if sc.comm.auth.identity == "per_process" else {}
    instance = new_run_instance()  # comm.auth.key_file signs for this start of the run only
    if sc.comm.auth.mode == "off":
        print("v2vsim: warning: comm.auth.identity is off: nothing is signed, and any process on this host (or on "
              "the zenoh bus) can alter this run's messages; report.md and metrics.json say so", file=sys.stderr)
    if remote_cavs:
        print("v2vsim: waiting for remote CAVs; on their hosts run:", file=sys.stderr)
        for c in remote_cavs:
            ident = ""
            if identities:  # carried to the agent's host by the operator, never over the bus
                path = out / "identity" / f"cav.{c}.json"
                write_identity_file(path, identities[f"cav.{c}"])
                ident = f"--identity {path} "
            inst = f"--run-instance {instance} " if sc.comm.auth.key_file is not None else ""
            print(f"  v2vsim agent {sc.source} --cav {c} --run-id {run_id} --cavs {','.join(cavs)} "
                  f"--egos {','.join(egos)} --frames {frames} {ident}{inst}"
                  + " ".join(f"--set {o}" for o in overrides), file=sys.stderr)
    display = ProgressDisplay(frames, sc.rate_hz, [f"ego.{e}" for e in egos])
    children: list[Child] = []
    failures: list[str] = []  # why the run failed, as said on the terminal
    interrupted = False
    code = 1
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        for attempt in range(1, PORT_ATTEMPTS + 1):
            endpoints = plan_endpoints(sc, procs)
            picked = {n for n, ep in endpoints.items() if ep and ep not in sc.transport.listen}
            children = []
            _start(children, sc, procs, endpoints, picked, overrides, run_id, cavs, egos, frames, out, display,
                   identities, instance, launch)
            try:
                code = _watch(children, display, failures)
                break
            except PortRace as race:
                _kill_quietly(children)
                display.reset()
                if attempt == PORT_ATTEMPTS:
                    display.message(f"v2vsim: error: {race}: another program took the port each time; "
                                    f"gave up after {PORT_ATTEMPTS} sets of free ports")
                    code = 1
                    break
                display.message(f"v2vsim: {race}: another program took the port after it was picked; "
                                f"picking new ports and restarting every process (attempt {attempt + 1} "
                                f"of {PORT_ATTEMPTS})")
    except KeyboardInterrupt:
        interrupted = True
        code = 130
        display.message("v2vsim: interrupted; stopping every process (partial results are written)")
    finally:
        _stop_all(children)
        display.close()
        signal.signal(signal.SIGTERM, previous)
    if code not in (0, 130):
        write_failure_metrics(out, sc, egos, failures)
    if code in (0, 130):
        merge_fleet(out, egos)  # several driven CAVs: the run's own metrics.json and report measure the fleet
    if not interrupted and code == 0:
        report = out / "report.md"
        if report.is_file():  # the last line says what metrics.json says: complete, or what happened instead
            print(terminal_line(ego_statuses(out, egos), str(report)), file=sys.stderr)
        else:
            print(f"v2vsim: error: the run ended but no report was written to {out}", file=sys.stderr)
            code = 1
    return code


def _start(children: list[Child], sc: Scenario, procs: list[str], endpoints: dict[str, str], picked: set[str],
           overrides: list[str], run_id: str, cavs: list[str], egos: list[str], frames: int, out: Path,
           display: ProgressDisplay, identities: dict[str, Identity], instance: str, launcher: Launcher) -> None:
    """Start every process (appending to `children` as it goes, so that Ctrl-C stops those already up),
    then one stderr reader per child (threads only after the forks: see v2vsim.launch.die_with_parent). Under
    comm.auth.identity per_process each child reads its identity from its stdin pipe: not in its argv (ps
    shows that), not in a file (another user process could read it)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", **{PROGRESS_ENV: "records"})
    for name in procs:
        role, ident = name.split(".", 1)
        module = {"driver": "agents.driver", "cav": "agents.cav", "ego": "agents.ego"}[role]
        argv = agent_argv(sc.source, overrides, run_id, endpoints[name],
                          [ep for n, ep in endpoints.items() if n != name and ep], cavs, egos, frames,
                          cav="" if role == "driver" else ident, out=str(out), identity="-" if identities else "",
                          run_instance=instance)
        # stdout joins stderr: nothing a child writes reaches the terminal except through the runner
        proc = launcher.start(module, argv, {**env, LAUNCHED_ENV: repr(time.time())}, stdin_pipe=bool(identities))
        if identities:
            assert proc.stdin is not None
            with proc.stdin:
                proc.stdin.write(identities[name].to_json().encode())
        children.append(Child(name, proc, endpoints[name], name in picked))
    for c in children:
        c.reader = threading.Thread(target=_pump, args=(c, display), name=f"stderr-{c.name}", daemon=True)
        c.reader.start()


def _pump(child: Child, display: ProgressDisplay) -> None:
    """Pass a child's stderr on: progress records to the display, every other line as it is (a line
    without a v2vsim prefix, e.g. a traceback, gets the process name so that crashes are attributable)."""
    assert child.proc.stdout is not None
    with child.proc.stdout:
        for raw in iter(child.proc.stdout.readline, b""):
            line = raw.decode("utf-8", "replace").rstrip("\r\n")
            if child.quiet:
                continue
            doc = parse_record(line)
            try:
                if doc is not None:
                    display.record(child.name, doc)
                elif child.picked and "address already in use" in line:
                    child.port_taken = True  # our port, not the user's transport.listen: the runner re-plans
                else:
                    display.message(line if line.startswith("v2vsim") else f"[{child.name}] {line}")
            except (OSError, ValueError):  # our own stderr is gone (e.g. `| head`): keep draining the pipe
                child.quiet = True  # so that the child never blocks on a full pipe


def _overrides_for_children(sc: Scenario) -> list[str]:
    """Children re-read the scenario file; command-line overrides travel with them."""
    return list(sc.overrides)


def _describe(name: str, rc: int) -> str:
    """How a child ended, for the run's error line."""
    who = "the simulator driver" if name == "driver.main" else name
    if rc < 0:
        return f"{who} died (signal {-rc}{_signame(-rc)})"
    if rc > 128 and rc - 128 < 65:  # an agent stopped by a signal it caught exits with 128 + N
        return f"{who} was stopped (signal {rc - 128}{_signame(rc - 128)})"
    return f"{who} exited with code {rc}"


def _signame(n: int) -> str:
    try:
        return f", {signal.Signals(n).name}"
    except ValueError:
        return ""


def _watch(children: list[Child], display: ProgressDisplay, failures: list[str]) -> int:
    """Wait for the egos to finish; fail fast when the driver or an ego fails (why: appended to `failures`);
    raise PortRace when a child could not listen on a port the runner picked."""
    driver = next(c for c in children if c.name == "driver.main")
    egos = [c for c in children if c.name.startswith("ego.")]
    while True:
        codes = {c.name: c.exited() for c in children}
        for c in children:
            rc = codes[c.name]
            if rc not in (None, 0) and c.picked and (rc == PORT_RACE_EXIT or c.port_taken):
                raise PortRace(c.name, c.endpoint)
        failed = [(c, codes[c.name]) for c in [driver, *egos] if codes[c.name] not in (None, 0)]
        if failed:
            for c, rc in failed:
                failures.append(_describe(c.name, rc))  # type: ignore[arg-type]
                display.message(f"v2vsim: error: {failures[-1]}")
            if codes[driver.name] not in (None, 0) and display.started:
                _wait_exit(egos, EGO_NOTICE_S)  # the egos write why they stopped, then exit
            rc = failed[0][1]
            return 2 if rc == 2 else 1
        if all(codes[e.name] == 0 for e in egos):
            return 0
        for c in children:
            rc = codes[c.name]
            # A CAV killed by a signal is a dead agent the ego copes with; one that exits with an
            # error is a failure to report (it would otherwise leave the driver waiting for it).
            if c.name.startswith("cav.") and rc is not None and 0 < rc < 128:
                failures.append(_describe(c.name, rc))
                display.message(f"v2vsim: error: {failures[-1]}")
                return 2 if rc == 2 else 1
        time.sleep(0.2)


def _wait_exit(children: list[Child], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    for c in children:
        with contextlib.suppress(subprocess.TimeoutExpired):
            c.proc.wait(timeout=max(0.0, deadline - time.monotonic()))


def _signal(c: Child, sig: int) -> None:
    """Signal a child's whole process group (it leads its own group)."""
    if c.proc.poll() is None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(c.proc.pid, sig)


def _kill_quietly(children: list[Child]) -> None:
    """SIGKILL every child of a start that is being replaced (it has not run a frame: nothing to save)."""
    for c in children:
        c.quiet = True
        _signal(c, signal.SIGKILL)
    for c in children:
        c.proc.wait()
        if c.reader is not None:
            c.reader.join(timeout=2.0)


def _stop_all(children: list[Child]) -> None:
    """SIGINT to every child still running, then SIGKILL after STOP_GRACE_S: no orphans."""
    for c in children:
        _signal(c, signal.SIGINT)
    deadline = time.monotonic() + STOP_GRACE_S
    for c in children:
        left = max(0.0, deadline - time.monotonic())
        try:
            c.proc.wait(timeout=left)
        except subprocess.TimeoutExpired:
            _signal(c, signal.SIGKILL)
            c.proc.wait()
    for c in children:  # their last words (errors, the ego's status) before the runner's own
        if c.reader is not None:
            c.reader.join(timeout=2.0)
