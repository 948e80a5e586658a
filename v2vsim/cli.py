"""`v2vsim` command line (DESIGN.md "Command line"). Each verb is a thin shell over a module."""

from __future__ import annotations

import argparse
import signal
import sys

from models.registration import PluginError  # (imports no torch)
from v2vsim import verbs
from v2vsim.config import ConfigError

IMAGE_BACKBONE_KINDS = ("resnet", "efficientnet_lite0")


def _scenario_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="scenario YAML, or the name of a shipped scenario (`v2vsim scenarios`)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override a scenario key, e.g. --set comm.drop.p=0.3 (repeatable)")


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
    p.set_defaults(func=verbs.cmd_run)

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
    p.set_defaults(func=verbs.cmd_evaluate)

    p = sub.add_parser("agent", help="run one CAV perception agent of a run started elsewhere (across hosts)")
    _scenario_args(p)
    p.add_argument("--cav", required=True)
    p.add_argument("--run-id", required=True)
    p.add_argument("--cavs", required=True, help="comma-separated CAV ids of the run")
    p.add_argument("--egos", required=True, help="comma-separated ego ids of the run")
    p.add_argument("--frames", type=int, default=0)
    p.add_argument("--identity", default=None, help="comm.auth.identity per_process: the identity file the run "
                                                   "issued this agent (the run prints the path)")
    p.add_argument("--run-instance", default="", help="comm.auth.key_file: the run instance the run printed")
    p.set_defaults(func=verbs.cmd_agent)

    p = sub.add_parser("router", help="a zenoh router for runs across hosts (transport.mode: client)")
    p.add_argument("--listen", action="append", default=None, help="endpoint, e.g. tcp/0.0.0.0:7447")
    p.set_defaults(func=verbs.cmd_router)

    p = sub.add_parser("frame", help="write one frame as files: world.json, LiDAR, camera images, GT masks")
    _scenario_args(p)
    p.add_argument("--at", type=float, required=True, help="simulated seconds after warm-up")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=verbs.cmd_frame)

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
    p.set_defaults(func=verbs.cmd_dataset)

    p = sub.add_parser("towns", help="generate towns: per seed a SUMO network, its buildings and a scenario YAML "
                                     "(needs netconvert: pip install 'v2vsim[towns]')")
    p.add_argument("--seeds", required=True, help="town seeds, A-B (inclusive) or A,B,C")
    p.add_argument("--out", required=True, help="folder: one town_<seed>/ per town, contact_sheet.png")
    p.add_argument("--no-sheet", action="store_true", help="skip the contact sheet of the first twelve towns")
    p.add_argument("--no-check", action="store_true", help="skip starting each town's traffic once")
    p.set_defaults(func=verbs.cmd_towns)

    p = sub.add_parser("train", help="train a model zoo (LiDAR, or camera with --encoder), stage by stage "
                                     "(docs/training.md)")
    p.add_argument("--data", required=True, help="dataset directory written by `v2vsim dataset`, or an OPV2V folder "
                                                 "(train/validate/test scenario folders; docs/dataset.md)")
    p.add_argument("--stage", default="all",
                   help="all | single | cache | compress (the wire's channel compressors, --ratios) | none | early | "
                        "attfuse | fcooper | v2vnet | cobevt | disconet | extrapolate (latency compensation for the "
                        "--out zoo's cobevt; not part of all) | align (a camera --encoder backward-aligned into the "
                        "--out LiDAR zoo's feature space, HEAL; not part of all) | the name of an installed fusion "
                        "plugin (`v2vsim models` lists them; not part of all)")
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
    p.add_argument("--distill-weight", type=float, default=None,
                   help="`align` stage: weight of the distillation from the LiDAR encoder's map of the same frame "
                        "(default 1; 0: off)")
    p.add_argument("--distill-focus", type=float, default=None,
                   help="`align` stage: extra distillation weight on the cells of vehicles the camera saw (cells of "
                        "vehicles it did not see then weigh 0; default 0: every cell alike)")
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
    p.set_defaults(func=verbs.cmd_train)

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
    p.add_argument("--include-degraded", action="store_true",
                   help="count degraded runs (agents lost, a method with no score) in the intervals, tables and "
                   "plots; by default they are only in sweep.csv/json, with their status")
    p.add_argument("--out", required=True, help="sweep directory (resumable: complete runs there are reused)")
    p.set_defaults(func=verbs.cmd_sweep)

    p = sub.add_parser("benchmark", help="the closed-loop benchmark: the catalogue's occlusion families x methods x "
                       "configurations x seeds, then leaderboard.md/csv/json and plots (docs/benchmark.md)")
    p.add_argument("--profile", default="quick", help="the catalogue's profile: quick (within 45 min on 2 cores), "
                   "leaderboard (docs/results.md's) or full (default quick)")
    p.add_argument("--catalogue", default=None, metavar="FILE",
                   help="a catalogue YAML (default: the shipped scenarios/benchmark/catalogue.yaml)")
    p.add_argument("--split", default="heldout", choices=["heldout", "tuning"],
                   help="which of the catalogue's seeds: heldout (the leaderboard's) or tuning (calibration)")
    p.add_argument("--families", default=None, help="comma-separated family names (default: all)")
    p.add_argument("--methods", default=None, help="comma-separated methods, oracle among them (default: the "
                   "profile's)")
    p.add_argument("--seeds", type=int, default=None, metavar="N", help="the split's first N seeds (default: the "
                   "profile's)")
    p.add_argument("--jobs", type=int, default=None, help="runs at a time (as sweep's --jobs)")
    p.add_argument("--engine", choices=["local", "dask"], default="local",
                   help="local: child processes here; dask: one task per run on a Dask distributed cluster")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS", help="with --engine dask: the scheduler")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="an override for every run of every family (repeatable)")
    p.add_argument("--bootstrap", type=int, default=1000, metavar="B", help="bootstrap resamples (default 1000)")
    p.add_argument("--stress", default=None, metavar="NAMES",
                   help="comma-separated degradation axes of the catalogue (latency, loss, burst_loss, pose, "
                   "penetration, attack, attack_defended): each "
                   "cooperative method x the axis's levels against none, and each method's breaking point "
                   "(breaking_points.md) instead of the leaderboard")
    p.add_argument("--driven", choices=["ego", "sees", "all"], default="ego",
                   help="who drives on what it perceives and receives: the ego alone (default), the ego and each "
                   "family's CAVs that see its hidden actor, or every CAV; the scores are then the fleet's")
    p.add_argument("--out", required=True, help="benchmark directory (resumable: complete runs there are reused)")
    p.set_defaults(func=verbs.cmd_benchmark)

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
    p.set_defaults(func=verbs.cmd_bandwidth)

    p = sub.add_parser("scenarios", help="list the shipped scenarios, one line each: the name SCENARIO accepts, "
                                         "what it is")
    p.set_defaults(func=verbs.cmd_scenarios)

    p = sub.add_parser("models", help="list every encoder and fusion method (installed plugins too, with where each "
                                      "comes from): parameters, stage shapes")
    p.add_argument("--preset", choices=["tiny", "paper"], default="tiny")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=verbs.cmd_models)

    p = sub.add_parser("view", help="open a run's recording.rrd in the Rerun viewer (or take screenshots)")
    p.add_argument("run", help="the run directory (or a .rrd file)")
    p.add_argument("--screenshots", metavar="DIR", default=None,
                   help="instead of opening a window, save PNGs of a headless viewer into DIR")
    p.add_argument("--at", default="0", help="with --screenshots: comma-separated frames (default 0)")
    p.set_defaults(func=verbs.cmd_view)

    p = sub.add_parser("bench", help="benchmarks: sensors | models | comm | run | startup | fleet | env | placement "
                       "| flood | defence")
    p.add_argument("what", choices=["sensors", "models", "comm", "run", "startup", "fleet", "env", "placement",
                                    "flood", "defence"])
    p.add_argument("rest", nargs=argparse.REMAINDER, help="options passed to the benchmark (see its --help)")
    p.set_defaults(func=verbs.cmd_bench)
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
