"""What each `v2vsim` verb does: one handler per verb (`cmd_<verb>`, called with the parsed arguments of
v2vsim.cli's parser), each a thin shell over a module, imported when the verb runs so that the command line
imports no torch to parse."""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from v2vsim.config import ConfigError, check_output_dir, load_scenario

_RUN_ID = re.compile(r"[A-Za-z0-9_.-]{1,64}")  # a zenoh key chunk (v2vsim/<run>/<kind>/<sender>)


def _method_names(value: str | None) -> str | None:
    """--methods "a, b" -> "a,b" (None when not given); ConfigError when it names no method (an empty --methods
    used to run every method). The names themselves are checked with the scenario (perception.methods)."""
    if value is None:
        return None
    names = [m.strip() for m in value.split(",") if m.strip()]
    if not names:
        raise ConfigError(f"--methods {value!r}: names no method; expected comma-separated methods, e.g. none,cobevt")
    return ",".join(names)


def cmd_run(args: argparse.Namespace) -> int:
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


def cmd_evaluate(args: argparse.Namespace) -> int:
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


def cmd_agent(args: argparse.Namespace) -> int:
    sc = load_scenario(args.scenario, args.overrides)  # a clear error before anything starts
    from v2vsim.perception.device import resolve_device

    try:  # this host's devices: the runner that printed this command checked its own
        resolve_device(sc.perception.device)
    except ConfigError as e:
        raise ConfigError(f"{sc.source}: {e}") from None
    from agents.cav import main as cav_main

    argv = [args.scenario, "--cav", args.cav, "--run-id", args.run_id, "--cavs", args.cavs, "--egos", args.egos,
            "--frames", str(args.frames)] + [x for o in args.overrides for x in ("--set", o)]
    if args.identity:
        argv += ["--identity", args.identity]
    if args.run_instance:
        argv += ["--run-instance", args.run_instance]
    return cav_main(argv)


def cmd_router(args: argparse.Namespace) -> int:
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


def cmd_frame(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario, args.overrides)
    from v2vsim.data.frame import write_frame

    written = write_frame(scenario, args.at, Path(args.out))
    print(f"wrote {len(written)} files to {args.out}")
    return 0


def cmd_dataset(args: argparse.Namespace) -> int:
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


def cmd_towns(args: argparse.Namespace) -> int:
    from v2vsim.data.record import parse_seeds
    from v2vsim.towns import generate_towns

    try:
        made = generate_towns(parse_seeds(args.seeds), Path(args.out), sheet=not args.no_sheet,
                              check=not args.no_check)
    except (ValueError, RuntimeError) as e:
        print(f"v2vsim: error: {e}", file=sys.stderr)
        return 2
    sheet = "" if args.no_sheet else f" (contact sheet: {args.out}/contact_sheet.png)"
    print(f"towns: {len(made)} in {args.out}{sheet}")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from v2vsim.data.layout import DatasetError
    from v2vsim.training.stages import TrainArgs
    from v2vsim.training.train import command_line, main_train

    overrides = {k: getattr(args, k) for k in ("epochs", "samples_per_epoch", "batch", "lr", "val_samples",
                                               "yaw_jitter_deg", "distill_weight",
                                               "distill_focus")
                 if getattr(args, k) is not None}
    if args.distill_focus is not None and args.stage != "align":
        print(f"v2vsim train: --distill-focus is an `align` stage option, not one of --stage {args.stage}",
              file=sys.stderr)
        return 2
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
    if args.bf16 and args.device == "cpu":
        from v2vsim.perception.precision import native_bf16

        if not native_bf16():  # autocast then emulates bfloat16: measured ~100x slower than float32 (AVX2 only)
            print("v2vsim train: warning: --bf16 on a CPU without AMX or AVX-512 BF16: bfloat16 is emulated there, "
                  "far slower than float32 (a fusion stage ran ~40 s a step against ~0.5 s); leave --bf16 out",
                  file=sys.stderr)
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


def cmd_scenarios(args: argparse.Namespace) -> int:
    from v2vsim.config import describe, shipped_scenarios

    shipped = shipped_scenarios()
    if not shipped:
        raise ConfigError("no shipped scenarios in this install (v2vsim/scenarios/ or the checkout's scenarios/)")
    width = max(map(len, shipped))
    for name, path in shipped.items():
        print(f"{name:<{width}}  {describe(path)}".rstrip())
    return 0


def cmd_models(args: argparse.Namespace) -> int:
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


def cmd_bench(args: argparse.Namespace) -> int:
    import importlib

    bench = importlib.import_module(f"v2vsim.bench.{args.what}")
    return int(bench.main(list(args.rest)) or 0)


def cmd_sweep(args: argparse.Namespace) -> int:
    from v2vsim.study.sweep import SweepArgs, sweep

    return sweep(SweepArgs(scenario=Path(args.scenario), grid=tuple(args.grid), seeds=args.seeds, out=Path(args.out),
                           frames=args.frames, jobs=args.jobs, overrides=tuple(args.overrides),
                           methods=_method_names(args.methods),
                           bootstrap=args.bootstrap, engine=args.engine, scheduler=args.scheduler,
                           replay=args.replay, include_degraded=args.include_degraded))


def cmd_benchmark(args: argparse.Namespace) -> int:
    from v2vsim.study.benchmark import BenchmarkArgs, benchmark

    def names(text: str | None) -> tuple[str, ...]:
        return tuple(n.strip() for n in text.split(",") if n.strip()) if text else ()

    return benchmark(BenchmarkArgs(out=Path(args.out), profile=args.profile,
                                   catalogue=Path(args.catalogue) if args.catalogue else None, split=args.split,
                                   families=names(args.families), methods=names(args.methods), seeds=args.seeds,
                                   jobs=args.jobs, engine=args.engine, scheduler=args.scheduler,
                                   overrides=tuple(args.overrides), bootstrap=args.bootstrap,
                                   stresses=names(args.stress), driven=args.driven))


def cmd_bandwidth(args: argparse.Namespace) -> int:
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


def cmd_view(args: argparse.Namespace) -> int:
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
