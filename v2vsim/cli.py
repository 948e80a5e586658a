"""`v2vsim` command line (DESIGN.md "Command line"). Each verb is a thin shell over a module."""

from __future__ import annotations

import argparse
import json
import re
import signal
import sys
from pathlib import Path

from models.registration import PluginError  # (imports no torch)
from v2vsim.config import ConfigError, check_output_dir, load_scenario

IMAGE_BACKBONE_KINDS = ("resnet", "efficientnet_lite0")

_RUN_ID = re.compile(r"[A-Za-z0-9_.-]{1,64}")  # a zenoh key chunk (v2vsim/<run>/<kind>/<sender>)


def _scenario_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="scenario YAML, or the name of a shipped scenario (`v2vsim scenarios`)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override a scenario key, e.g. --set comm.drop.p=0.3 (repeatable)")


def _method_names(value: str | None) -> str | None:
    """--methods "a, b" -> "a,b" (None when not given); ConfigError when it names no method (an empty --methods
    used to run every method). The names themselves are checked with the scenario (perception.methods)."""
    if value is None:
        return None
    names = [m.strip() for m in value.split(",") if m.strip()]
    if not names:
        raise ConfigError(f"--methods {value!r}: names no method; expected comma-separated methods, e.g. none,cobevt")
    return ",".join(names)


def _cmd_run(args: argparse.Namespace) -> int:
    overrides = list(args.overrides)
    methods = _method_names(args.methods)
    if methods:
        overrides.append(f"perception.methods=[{methods}]")
    scenario = load_scenario(args.scenario, overrides)  # validate before the heavy imports
    if args.frames is not None and args.frames < 1:  # 0 used to mean "the whole duration", -1 "nothing"
        raise ConfigError(f"--frames {args.frames}: expected a number of frames >= 1 "
                          f"(without --frames: duration_s x rate_hz = {scenario.frames})")
    if args.run_id is not None and not _RUN_ID.fullmatch(args.run_id):
        raise ConfigError(f"--run-id {args.run_id!r}: allowed: letters, digits, '_', '-' and '.'")
    out = Path(args.out) if args.out else Path(scenario.output.dir)
    check_output_dir(out, "--out" if args.out else f"{scenario.source}: output.dir")
    remote = tuple(c for c in (args.remote_cavs or "").split(",") if c)
    from v2vsim.runner import run

    return run(scenario, out, frames=args.frames, remote_cavs=remote, run_id=args.run_id)


def _cmd_evaluate(args: argparse.Namespace) -> int:
    overrides = list(args.overrides)
    methods = _method_names(args.methods)
    if methods:
        overrides.append(f"perception.methods=[{methods}]")
    if args.frames is not None and args.frames < 1:
        raise ConfigError(f"--frames {args.frames}: expected a number of frames >= 1")
    from agents.evaluate import evaluate_points, read_plan

    if args.plan is not None:
        if args.grid or args.out is not None:
            raise ConfigError("--plan names every point's folder and overrides: it takes no --grid or --out")
        points = [([*o, *overrides], out) for o, out in read_plan(Path(args.plan))]
    elif args.out is None:
        raise ConfigError("--out: required (the output folder; with --grid, each point in a subfolder of it)")
    elif args.grid:
        from v2vsim.study.grid import parse_axes
        from v2vsim.study.grid import points as grid_points

        axes = parse_axes(args.grid)
        points = [([*p.overrides(axes), *overrides], Path(args.out) / p.pid) for p in grid_points(axes)]
    else:
        points = [(overrides, Path(args.out))]
    return evaluate_points(Path(args.recording), points, frames=args.frames)


def _cmd_agent(args: argparse.Namespace) -> int:
    load_scenario(args.scenario, args.overrides)  # a clear error before anything starts
    from agents.cav import main as cav_main

    argv = [args.scenario, "--cav", args.cav, "--run-id", args.run_id, "--cavs", args.cavs, "--egos", args.egos,
            "--frames", str(args.frames)] + [x for o in args.overrides for x in ("--set", o)]
    if args.identity:
        argv += ["--identity", args.identity]
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
    from v2vsim.data.frame import write_frame

    written = write_frame(scenario, args.at, Path(args.out))
    print(f"wrote {len(written)} files to {args.out}")
    return 0


def _cmd_dataset(args: argparse.Namespace) -> int:
    from v2vsim.data.layout import DatasetError
    from v2vsim.data.record import parse_seeds, record_dataset

    record = record_dataset
    if args.format == "opv2v":
        from v2vsim.data.opv2v_write import NATIVE_DIR, record_opv2v_dataset

        record = record_opv2v_dataset
    try:
        seeds = parse_seeds(args.seeds)
        out = record(args.scenario, seeds, args.frames, Path(args.out), split=args.split,
                     overrides=tuple(args.overrides), cameras=args.cameras,
                     traffic_only=args.traffic_only, jobs=args.jobs)
    except (ValueError, DatasetError) as e:
        print(f"v2vsim: error: {e}", file=sys.stderr)
        return 2
    if args.format == "opv2v":
        print(f"traffic: {out}/{NATIVE_DIR}/*/traffic" if args.traffic_only else
              f"dataset: {out} (OPV2V layout; recorded from {out}/{NATIVE_DIR}/manifest.json)")
    else:
        print(f"traffic: {out}/*/traffic" if args.traffic_only else f"dataset: {out}/manifest.json")
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from v2vsim.data.layout import DatasetError
    from v2vsim.training.stages import TrainArgs
    from v2vsim.training.train import command_line, main_train

    overrides = {k: getattr(args, k) for k in ("epochs", "samples_per_epoch", "batch", "lr", "val_samples",
                                               "yaw_jitter_deg")
                 if getattr(args, k) is not None}
    extra = {}
    if args.ratios is not None:
        try:
            extra["ratios"] = tuple(int(r) for r in args.ratios.split(","))
        except ValueError:
            print(f"v2vsim train: --ratios {args.ratios!r}: expected integers separated by commas, e.g. 8,16",
                  file=sys.stderr)
            return 2
        if any(r < 2 for r in extra["ratios"]):
            print(f"v2vsim train: --ratios {args.ratios!r}: every ratio must be >= 2", file=sys.stderr)
            return 2
    targs = TrainArgs(data=Path(args.data), stage=args.stage, out=Path(args.out), work=Path(args.work),
                      encoder=args.encoder, preset=args.preset, cells=args.cells, bf16=args.bf16,
                      wire_ratio=args.wire_ratio, image_backbone=args.image_backbone, **extra,
                      device=args.device, threads=args.threads, seed=args.seed, resume=args.resume,
                      val_every=args.val_every, workers=args.workers,
                      overrides=tuple(overrides.items()), command=command_line(sys.argv[2:]))
    if args.device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            print("v2vsim: error: --device cuda: no CUDA device here (this torch build: "
                  f"{torch.__version__}); use --device cpu", file=sys.stderr)
            return 2
    from models.efficientnet_lite import PretrainedWeightsMissing

    try:
        return main_train(targs)
    except (ValueError, DatasetError, PretrainedWeightsMissing) as e:
        print(f"v2vsim: error: {e}", file=sys.stderr)
        return 2


def _cmd_scenarios(args: argparse.Namespace) -> int:
    from v2vsim.config import describe, shipped_scenarios

    shipped = shipped_scenarios()
    if not shipped:
        raise ConfigError("no shipped scenarios in this install (v2vsim/scenarios/ or the checkout's scenarios/)")
    width = max(map(len, shipped))
    for name, path in shipped.items():
        print(f"{name:<{width}}  {describe(path)}".rstrip())
    return 0


def _cmd_models(args: argparse.Namespace) -> int:
    """The table (or --json rows) of every encoder and fusion method, plugins with where they come from; a fusion
    plugin that cannot be used is listed as broken with the reason, and then the exit code is 2."""
    from models.describe import describe_models, format_models_table

    rows = describe_models(args.preset)
    print(json.dumps(rows, indent=2) if args.json else format_models_table(rows))
    broken = [r for r in rows if r.get("error")]
    if broken:
        print(f"v2vsim: error: {len(broken)} fusion plugin(s) cannot be used: "
              f"{', '.join(r['name'] for r in broken)} (the reason is in the table)", file=sys.stderr)
        return 2
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    import importlib

    bench = importlib.import_module(f"v2vsim.bench.{args.what}")
    return int(bench.main(list(args.rest)) or 0)


def _cmd_sweep(args: argparse.Namespace) -> int:
    from v2vsim.study.sweep import SweepArgs, sweep

    return sweep(SweepArgs(scenario=Path(args.scenario), grid=tuple(args.grid), seeds=args.seeds, out=Path(args.out),
                           frames=args.frames, jobs=args.jobs, overrides=tuple(args.overrides),
                           methods=_method_names(args.methods),
                           bootstrap=args.bootstrap, engine=args.engine, scheduler=args.scheduler,
                           replay=args.replay))


def _cmd_bandwidth(args: argparse.Namespace) -> int:
    from v2vsim.data.record import parse_seeds
    from v2vsim.env.bandwidth import bandwidth_curve, parse_fractions

    try:
        seeds, fractions = parse_seeds(args.seeds), parse_fractions(args.fractions)
    except ValueError as e:
        print(f"v2vsim: error: {e}", file=sys.stderr)
        return 2
    if args.frames < 1:
        raise ConfigError(f"--frames {args.frames}: expected a number of frames >= 1")
    methods = str(_method_names(args.methods)).split(",")
    overrides = dict(o.split("=", 1) for o in args.overrides if "=" in o)
    bad = [o for o in args.overrides if "=" not in o]
    if bad:
        raise ConfigError(f"--set {bad[0]!r}: expected KEY.PATH=VALUE")
    import yaml

    bandwidth_curve(args.scenario, fractions, seeds, args.frames, methods, Path(args.out),
                    overrides={k: yaml.safe_load(v) for k, v in overrides.items()})
    print(f"bandwidth: {Path(args.out) / 'bandwidth.md'}")
    return 0


def _cmd_view(args: argparse.Namespace) -> int:
    from v2vsim.recording.view import ViewError, find_recording, open_viewer, screenshots

    try:
        rrd = find_recording(Path(args.run))
        if args.screenshots is None:
            return open_viewer(rrd)
        try:
            frames = [int(f) for f in args.at.split(",") if f.strip()]
        except ValueError:
            raise ViewError(f"--at: expected frame numbers like 0,50,100, got {args.at!r}") from None
        for path in screenshots(rrd, Path(args.screenshots), frames or [0]):
            print(path)
        return 0
    except ViewError as e:
        print(f"v2vsim view: error: {e}", file=sys.stderr)
        return 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="v2vsim", description=__doc__)
    sub = parser.add_subparsers(dest="verb", required=True)

    p = sub.add_parser("run", help="run the co-simulation: report.md, metrics.json, recording.rrd, plots")
    _scenario_args(p)
    p.add_argument("--frames", type=int, default=None, help="stop after N >= 1 frames (default: duration_s * rate_hz)")
    p.add_argument("--out", default=None, help="output directory (default: output.dir)")
    p.add_argument("--methods", default=None, help="comma-separated fusion methods, e.g. none,cobevt")
    p.add_argument("--remote-cavs", default=None, help="CAV ids started on other hosts with `v2vsim agent`")
    p.add_argument("--run-id", default=None, help="run id (default: random); remote agents must use the same")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("evaluate", help="replay the ego over a recorded run (output.record_messages) with other "
                       "receiver-side keys or methods: no SUMO, sensing or encoding (docs/run.md)")
    p.add_argument("recording", help="a run folder with messages/ (or the messages/ folder itself)")
    p.add_argument("--methods", default=None, help="comma-separated fusion methods, e.g. none,late,cobevt")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override a receiver-side key, e.g. --set comm.drop.p=0.3 (repeatable)")
    p.add_argument("--frames", type=int, default=None, help="replay only the first N frames")
    p.add_argument("--grid", action="append", default=[], metavar="KEY.PATH=V1,V2,...",
                   help="replay every point of this grid of receiver-side keys in one pass, each into "
                   "OUT/<point>/ (repeatable: the Cartesian product)")
    p.add_argument("--plan", default=None, metavar="FILE",
                   help='points to replay in one pass, as JSON: [{"out": DIR, "overrides": ["KEY=VALUE", ...]}, ...] '
                   "(what v2vsim sweep writes; instead of --out and --grid)")
    p.add_argument("--out", default=None, help="output directory: metrics.json, report.md, plots")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("agent", help="run one CAV perception agent of a run started elsewhere (across hosts)")
    _scenario_args(p)
    p.add_argument("--cav", required=True)
    p.add_argument("--run-id", required=True)
    p.add_argument("--cavs", required=True, help="comma-separated CAV ids of the run")
    p.add_argument("--egos", required=True, help="comma-separated ego ids of the run")
    p.add_argument("--frames", type=int, default=0)
    p.add_argument("--identity", default=None, help="comm.auth.identity per_process: the identity file the run "
                                                   "issued this agent (the run prints the path)")
    p.set_defaults(func=_cmd_agent)

    p = sub.add_parser("router", help="a zenoh router for runs across hosts (transport.mode: client)")
    p.add_argument("--listen", action="append", default=None, help="endpoint, e.g. tcp/0.0.0.0:7447")
    p.set_defaults(func=_cmd_router)

    p = sub.add_parser("frame", help="write one frame as files: world.json, LiDAR, camera images, GT masks")
    _scenario_args(p)
    p.add_argument("--at", type=float, required=True, help="simulated seconds after warm-up")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=_cmd_frame)

    p = sub.add_parser("dataset", help="record runs as a training dataset (docs/dataset.md)")
    _scenario_args(p)
    p.add_argument("--seeds", required=True, help="seeds, A-B (inclusive) or A,B,C")
    p.add_argument("--frames", type=int, required=True, help="frames per seed")
    p.add_argument("--out", required=True, help="dataset directory (runs are added to its manifest)")
    p.add_argument("--split", default="train", choices=["train", "val", "eval"],
                   help="split of these seeds; a scenario's seeds may belong to one split only")
    p.add_argument("--cameras", action="store_true", help="also record the four camera images of every CAV")
    p.add_argument("--traffic-only", action="store_true",
                   help="only simulate and save each run's traffic (<run>/traffic/); a later call senses from it, "
                        "without the simulator")
    p.add_argument("--jobs", type=int, default=1, help="seeds sensed at once, one process each (default 1)")
    p.add_argument("--format", choices=["v2vsim", "opv2v"], default="v2vsim",
                   help="v2vsim (default) or opv2v: OPV2V's layout (train/validate/test scenario folders, .pcd, "
                        ".yaml, camera and BEV PNGs) beside the v2vsim recording it is made from (docs/dataset.md)")
    p.set_defaults(func=_cmd_dataset)

    p = sub.add_parser("train", help="train a model zoo (LiDAR, or camera with --encoder), stage by stage "
                                     "(docs/training.md)")
    p.add_argument("--data", required=True, help="dataset directory written by `v2vsim dataset`, or an OPV2V folder "
                                                 "(train/validate/test scenario folders; docs/dataset.md)")
    p.add_argument("--stage", default="all",
                   help="all | single | cache | compress (the wire's channel compressors, --ratios) | none | early | "
                        "attfuse | fcooper | v2vnet | cobevt | disconet | extrapolate (latency compensation for the "
                        "--out zoo's cobevt; not part of all) | the name of an installed fusion plugin (`v2vsim "
                        "models` lists them; not part of all)")
    p.add_argument("--out", default="models/weights", help="zoo directory: manifest.json + <encoder>_<preset>/")
    p.add_argument("--work", default="runs/train", help="checkpoints and the feature cache (resumable)")
    p.add_argument("--resume", action="store_true", help="continue the stage from its last checkpoint")
    p.add_argument("--encoder", choices=["pointpillars", "sinbevt", "lara"], default="pointpillars",
                   help="the zoo to train: pointpillars (LiDAR) or a camera encoder (needs a --cameras dataset)")
    p.add_argument("--preset", choices=["tiny", "paper"], default="tiny")
    p.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--epochs", type=int, default=None, help="override the stage's default")
    p.add_argument("--samples-per-epoch", type=int, default=None, help="override the stage's default")
    p.add_argument("--batch", type=int, default=None, help="override the stage's default")
    p.add_argument("--lr", type=float, default=None, help="override the stage's default (peak, one-cycle)")
    p.add_argument("--val-samples", type=int, default=None, help="validation samples after each epoch")
    p.add_argument("--val-every", type=int, default=1, help="validate every N epochs (and after the last)")
    p.add_argument("--yaw-jitter", dest="yaw_jitter_deg", type=float, default=None, metavar="DEG",
                   help="camera `single` stage: turn each sample's agent frame by a uniform angle in [-DEG, DEG] "
                   "(extrinsics and targets alike; default 0: off)")
    p.add_argument("--workers", type=int, default=0,
                   help="data-loading processes (default 0: in the training process; a GPU wants several)")
    p.add_argument("--cells", type=int, default=None, choices=[32, 64, 128],
                   help="LiDAR fusion grid F x F over the BEV square (default: the --out zoo's, else the preset's)")
    p.add_argument("--ratios", default=None, metavar="R,R,...",
                   help="`compress` stage: the channel compression ratios to train (default 8,16,32,64)")
    p.add_argument("--bf16", action="store_true",
                   help="bfloat16 autocast in the forward pass (a CPU with AMX, or CUDA); docs/training.md")
    p.add_argument("--wire-ratio", type=int, default=None, metavar="R",
                   help="an intermediate fusion stage: train it on the ratio-R wire instead of the zoo's (its own "
                        "checkpoint <method>_r<R>.pt, loaded by runs with comm.channel_compression: R; 1: "
                        "uncompressed); docs/training.md")
    # the kinds of models.image_backbone.IMAGE_BACKBONES (named here: the CLI imports no torch to parse)
    p.add_argument("--image-backbone", default=None, choices=IMAGE_BACKBONE_KINDS,
                   help="a camera encoder's image backbone (default: the --out zoo's, else the preset's: "
                        "ImageNet EfficientNet-Lite0 for tiny); models/image_backbone.py")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("sweep", help="run a scenario over a grid of overrides x seeds: sweep.csv/json/md, plots "
                       "with 95%% bootstrap intervals")
    _scenario_args(p)
    p.add_argument("--grid", action="append", default=[], metavar="KEY.PATH=V1,V2,...",
                   help="a swept key and its values, parsed like --set (repeatable: the Cartesian product)")
    p.add_argument("--seeds", required=True, help="seeds, A-B (inclusive) or A; the same seeds at every point")
    p.add_argument("--frames", type=int, default=None, help="frames per run (default: duration_s * rate_hz)")
    p.add_argument("--methods", default=None, help="comma-separated fusion methods, e.g. none,cobevt")
    p.add_argument("--jobs", type=int, default=None,
                   help="runs at a time (default 1, or the cluster's worker threads under --engine dask); one "
                   "simulated run keeps about 2 cores busy (its processes), so 2 replays run in its place")
    p.add_argument("--engine", choices=["local", "dask"], default="local",
                   help="local: child processes here; dask: one task per run on a Dask distributed cluster")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="with --engine dask: the scheduler, e.g. tcp://10.0.0.1:8786")
    p.add_argument("--bootstrap", type=int, default=1000, metavar="B", help="bootstrap resamples (default 1000)")
    p.add_argument("--no-replay", dest="replay", action="store_false",
                   help="simulate every run (default: record the first point of each seed and replay the points "
                   "that differ from it only in receiver-side keys with `v2vsim evaluate`)")
    p.add_argument("--out", required=True, help="sweep directory (resumable: complete runs there are reused)")
    p.set_defaults(func=_cmd_sweep)

    p = sub.add_parser("bandwidth", help="bandwidth vs accuracy: fixed shares of BEV cells sent, in the env "
                                         "(v2vsim.env): bandwidth.csv/md/png")
    _scenario_args(p)
    p.add_argument("--fractions", default="0,0.05,0.1,0.25,0.5,1",
                   help="shares of each CAV's feature cells to send (default 0,0.05,0.1,0.25,0.5,1)")
    p.add_argument("--seeds", required=True, help="A-B or A,B,C (held-out seeds: not the zoo's training seeds)")
    p.add_argument("--frames", type=int, default=50, help="frames per seed and share (default 50)")
    p.add_argument("--methods", default="attfuse,fcooper,v2vnet,disconet,cobevt",
                   help="fusion methods the ego runs (none is always added)")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=_cmd_bandwidth)

    p = sub.add_parser("scenarios", help="list the shipped scenarios, one line each: the name SCENARIO accepts, "
                                         "what it is")
    p.set_defaults(func=_cmd_scenarios)

    p = sub.add_parser("models", help="list every encoder and fusion method (installed plugins too, with where each "
                                      "comes from): parameters, stage shapes")
    p.add_argument("--preset", choices=["tiny", "paper"], default="tiny")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_cmd_models)

    p = sub.add_parser("view", help="open a run's recording.rrd in the Rerun viewer (or take screenshots)")
    p.add_argument("run", help="the run directory (or a .rrd file)")
    p.add_argument("--screenshots", metavar="DIR", default=None,
                   help="instead of opening a window, save PNGs of a headless viewer into DIR")
    p.add_argument("--at", default="0", help="with --screenshots: comma-separated frames (default 0)")
    p.set_defaults(func=_cmd_view)

    p = sub.add_parser("bench", help="benchmarks: sensors | models | comm | run | env | placement | flood")
    p.add_argument("what", choices=["sensors", "models", "comm", "run", "env", "placement", "flood"])
    p.add_argument("rest", nargs=argparse.REMAINDER, help="options passed to the benchmark (see its --help)")
    p.set_defaults(func=_cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    # A shell starts background commands (`cmd &` without job control) with SIGINT ignored, and Python
    # then never raises KeyboardInterrupt: Ctrl-C and the runner's SIGINT must still stop every verb.
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    args = build_parser().parse_args(argv)
    if getattr(args, "verb", None) == "router" and not args.listen:
        args.listen = ["tcp/127.0.0.1:7447"]
    try:
        return int(args.func(args) or 0)
    except (ConfigError, PluginError) as e:  # PluginError: a fusion plugin that cannot be used (models.registry)
        print(f"v2vsim: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("v2vsim: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
