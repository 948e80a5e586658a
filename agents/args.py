"""The command line every agent process reads (`AgentArgs`, built by the runner with `agent_argv`), and what it
signs with under comm.auth: the shared run key (comm.auth.key_file) or its own Identity (comm.auth.identity
per_process: on stdin from a local runner, or an identity file on another host, docs/cluster.md)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from agents.timing import Startup
from v2vsim.comm.identity import Identity, IdentityError, parse_identity, shared_run_key
from v2vsim.comm.signing import Signer
from v2vsim.config import ConfigError, Scenario, load_scenario


def read_key(path: str | None) -> bytes | None:
    """The run key of comm.auth.key_file (None: no shared key)."""
    return None if path is None else open(path, "rb").read().strip()


def run_signer(args: AgentArgs) -> Signer | None:
    """What this process signs with and checks others' messages by: its Identity under comm.auth.identity
    per_process, the shared run key under comm.auth.key_file (bound to this run instance), None with comm.auth
    off."""
    if args.identity is not None:
        return args.identity
    secret = read_key(args.scenario.comm.auth.key_file)
    if secret is None or not args.run_instance:  # no instance: only a replay of a recording from before issue 45,
        return secret  # whose messages were signed with the file's secret itself (a live agent must give one)
    return shared_run_key(secret, args.run_id, args.run_instance)


def load_identity(spec: str, sc: Scenario, run_id: str, name: str) -> Identity:
    """The Identity the runner issued this process: '-' = on stdin (a local child), else an identity file
    (an agent on another host, docs/cluster.md). IdentityError says what is wrong."""
    where = "the identity on stdin" if spec == "-" else f"--identity {spec}"
    try:
        raw = sys.stdin.buffer.read() if spec == "-" else Path(spec).read_bytes()
    except OSError as e:
        raise IdentityError(f"{where}: cannot read it: {e.strerror or e}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:  # was a traceback: not the JSON file the runner wrote
        raise IdentityError(f"{where}: not an identity file (not UTF-8 text; the runner writes JSON, "
                            "docs/cluster.md)") from None
    return parse_identity(text, "the identity on stdin" if spec == "-" else spec, run_id=run_id, name=name)


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
    identity: Identity | None = None  # comm.auth.identity per_process: this process's credentials
    run_instance: str = ""  # this start of the run (v2vsim.comm.identity.new_run_instance): bound into signatures
    # where this process's start-up went (agents.timing): marked as it gets there, written with its timing
    startup: Startup = field(default_factory=Startup, compare=False)


def parse_agent_args(role: str, argv: list[str] | None = None) -> AgentArgs:
    startup = Startup()
    startup.mark("imports")  # main() began: the interpreter and the imports are behind
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
    p.add_argument("--identity", default=None,
                   help="comm.auth.identity per_process: '-' (on stdin) or the identity file the runner issued")
    p.add_argument("--run-instance", default="", help="this start of the run, as the runner printed it")
    a = p.parse_args(argv)
    try:
        sc = load_scenario(a.scenario, a.overrides)
    except ConfigError as e:
        print(f"v2vsim-{role}: error: {e}", file=sys.stderr)
        sys.exit(2)
    identity = None
    name = f"{role}.{a.cav or 'main'}"
    if sc.comm.auth.identity == "per_process":
        if a.identity is None:
            print(f"v2vsim-{role}: error: comm.auth.identity is per_process and no --identity was given (the "
                  "runner prints each remote agent's command line with its identity file)", file=sys.stderr)
            sys.exit(2)
        try:
            identity = load_identity(a.identity, sc, a.run_id, name)
        except IdentityError as e:
            print(f"v2vsim-{role}: error: {e}", file=sys.stderr)
            sys.exit(2)
    elif a.identity is not None:  # was ignored, and the agent then waited without a word for a run it cannot join
        print(f"v2vsim-{role}: error: --identity {a.identity}: this scenario's comm.auth.identity is "
              f"{sc.comm.auth.identity}, so an identity file is not used; give the same --set options as the run "
              "(its printed agent command line has them, e.g. --set comm.auth.identity=per_process)", file=sys.stderr)
        sys.exit(2)
    if sc.comm.auth.key_file is not None and not a.run_instance:
        print(f"v2vsim-{role}: error: comm.auth.key_file signs for one run instance and no --run-instance was "
              "given (the runner prints each remote agent's command line with it)", file=sys.stderr)
        sys.exit(2)
    split = lambda s: tuple(x for x in s.split(",") if x)  # noqa: E731
    return AgentArgs(scenario=sc, scenario_path=a.scenario, overrides=tuple(a.overrides), run_id=a.run_id,
                     listen=a.listen, peers=tuple(a.peers), cavs=split(a.cavs), egos=split(a.egos), cav=a.cav,
                     frames=a.frames or sc.frames, out=a.out, identity=identity, run_instance=a.run_instance,
                     startup=startup)


def agent_argv(args_scenario: str, overrides: Iterable[str], run_id: str, listen: str, peers: Iterable[str],
               cavs: Iterable[str], egos: Iterable[str], frames: int, cav: str = "", out: str = "",
               identity: str = "", run_instance: str = "") -> list[str]:
    """The command-line tail that `parse_agent_args` reads (the runner builds it)."""
    argv = [args_scenario, "--run-id", run_id, "--cavs", ",".join(cavs), "--egos", ",".join(egos),
            "--frames", str(frames)]
    if run_instance:
        argv += ["--run-instance", run_instance]
    if identity:
        argv += ["--identity", identity]
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
