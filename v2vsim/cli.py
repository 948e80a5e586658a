"""`v2vsim` command line (DESIGN.md "Command line"). Each verb is a thin shell over a module."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from v2vsim.config import ConfigError, load_scenario


def _scenario_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="scenario YAML")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override a scenario key, e.g. --set comm.drop.p=0.3 (repeatable)")


def _cmd_run(args: argparse.Namespace) -> int:
    overrides = list(args.overrides)
    if args.methods:
        overrides.append(f"perception.methods=[{args.methods}]")
    scenario = load_scenario(args.scenario, overrides)  # validate before the heavy imports
    from v2vsim.runner import run

    out = Path(args.out) if args.out else Path(scenario.output.dir)
    remote = tuple(c for c in (args.remote_cavs or "").split(",") if c)
    return run(scenario, out, frames=args.frames, remote_cavs=remote, run_id=args.run_id)


def _cmd_agent(args: argparse.Namespace) -> int:
    load_scenario(args.scenario, args.overrides)  # a clear error before anything starts
    from agents.cav import main as cav_main

    argv = [args.scenario, "--cav", args.cav, "--run-id", args.run_id, "--cavs", args.cavs, "--egos", args.egos,
            "--frames", str(args.frames)] + [x for o in args.overrides for x in ("--set", o)]
    return cav_main(argv)


def _cmd_router(args: argparse.Namespace) -> int:
    import time

    from v2vsim.comm.transport import TransportError, open_session
    from v2vsim.config import TransportConfig

    try:
        session = open_session(TransportConfig(mode="router", listen=tuple(args.listen)))  # type: ignore[arg-type]
    except TransportError as e:
        print(f"v2vsim: error: {e}", file=sys.stderr)
        return 2
    print(f"v2vsim: zenoh router listening on {', '.join(args.listen)} (Ctrl-C to stop)", file=sys.stderr)
    try:
        while True:
            time.sleep(1)
    finally:
        session.close()


def _cmd_frame(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario, args.overrides)
    from v2vsim.frame import write_frame

    written = write_frame(scenario, args.at, Path(args.out))
    print(f"wrote {len(written)} files to {args.out}")
    return 0


def _cmd_models(args: argparse.Namespace) -> int:
    from models.registry import describe_models, format_models_table

    rows = describe_models(args.preset)
    print(json.dumps(rows, indent=2) if args.json else format_models_table(rows))
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "sensors":
        from v2vsim.bench_sensors import main as bench

        return int(bench(list(args.rest)) or 0)
    import runpy

    script = Path(__file__).resolve().parents[1] / "benchmarks" / f"bench_{args.what}.py"
    if not script.is_file():
        print(f"v2vsim: error: {script} not found (benchmarks run from a source checkout)", file=sys.stderr)
        return 2
    sys.argv = [str(script), *args.rest]
    runpy.run_path(str(script), run_name="__main__")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="v2vsim", description=__doc__)
    sub = parser.add_subparsers(dest="verb", required=True)

    p = sub.add_parser("run", help="run the co-simulation: report.md, metrics.json, recording.rrd, plots")
    _scenario_args(p)
    p.add_argument("--frames", type=int, default=None, help="stop after N frames (default: duration_s * rate_hz)")
    p.add_argument("--out", default=None, help="output directory (default: output.dir)")
    p.add_argument("--methods", default=None, help="comma-separated fusion methods, e.g. none,cobevt")
    p.add_argument("--remote-cavs", default=None, help="CAV ids started on other hosts with `v2vsim agent`")
    p.add_argument("--run-id", default=None, help="run id (default: random); remote agents must use the same")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("agent", help="run one CAV perception agent of a run started elsewhere (across hosts)")
    _scenario_args(p)
    p.add_argument("--cav", required=True)
    p.add_argument("--run-id", required=True)
    p.add_argument("--cavs", required=True, help="comma-separated CAV ids of the run")
    p.add_argument("--egos", required=True, help="comma-separated ego ids of the run")
    p.add_argument("--frames", type=int, default=0)
    p.set_defaults(func=_cmd_agent)

    p = sub.add_parser("router", help="a zenoh router for runs across hosts (transport.mode: client)")
    p.add_argument("--listen", action="append", default=None, help="endpoint, e.g. tcp/0.0.0.0:7447")
    p.set_defaults(func=_cmd_router)

    p = sub.add_parser("frame", help="write one frame as files: world.json, LiDAR, camera images, GT masks")
    _scenario_args(p)
    p.add_argument("--at", type=float, required=True, help="simulated seconds after warm-up")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=_cmd_frame)

    p = sub.add_parser("models", help="list every encoder and fusion method: parameters, stage shapes")
    p.add_argument("--preset", choices=["tiny", "paper"], default="tiny")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_cmd_models)

    p = sub.add_parser("bench", help="benchmarks: sensors | models | comm")
    p.add_argument("what", choices=["sensors", "models", "comm"])
    p.add_argument("rest", nargs=argparse.REMAINDER, help="options passed to the benchmark (see its --help)")
    p.set_defaults(func=_cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "verb", None) == "router" and not args.listen:
        args.listen = ["tcp/127.0.0.1:7447"]
    try:
        return int(args.func(args) or 0)
    except ConfigError as e:
        print(f"v2vsim: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("v2vsim: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
