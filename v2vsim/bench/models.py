"""Benchmark the models on CPU, one thread: parameters and forward latency per encoder, per fusion
method for N = 1, 2, 4, 8 agents, the decoder + heads, and the tiny per-frame budget
(PointPillars on one 32k-point sweep + warp + FuseBEVT over 4 agents, target < 50 ms).

    v2vsim bench models [--presets tiny,paper] [--cells 32,64,128] [--repeats 5] [--json out.json]
    v2vsim bench models --train-step [--presets tiny] [--cells 64] [--threads 2]

--cells: the LiDAR fusion grids to time (PointPillars, every fusion method, the LiDAR heads and the frame at
each; default: each preset's own); the camera encoders keep their own 32 x 32 grid.

Median of `repeats` timed runs after 2 warm-up runs, torch.no_grad, eval mode. Not a test: figures
depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable

import torch

from models.build import build_encoder, build_fusion, build_heads
from models.presets import get_preset
from models.registry import ENCODERS, FUSION
from models.warp import warp_to_ego

AGENTS = (1, 2, 4, 8)


def _time_ms(fn: Callable[[], object], repeats: int, warmup: int = 2) -> float:
    with torch.no_grad():
        for _ in range(warmup):
            fn()
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def _params(m: torch.nn.Module) -> int:
    return sum(p.numel() for p in m.parameters())


def _poses(n: int) -> torch.Tensor:
    p = torch.zeros(1, n, 3)
    p[0, 1:] = torch.tensor([12.0, -5.0, 0.7])
    return p


def bench_preset(preset: str, repeats: int, cells: int | None = None) -> list[dict]:
    """Rows {preset, kind, name, agents, params, ms} for one preset at LiDAR grid `cells` (default its own);
    the preset column reads "<preset> FxF"."""
    p = get_preset(preset)
    f = cells or p.cells
    label = f"{preset} {f}x{f}"
    rows: list[dict] = []
    encoders: dict[str, torch.nn.Module] = {}
    for name in ENCODERS:
        if cells is not None and name != "pointpillars":
            continue  # a camera encoder's grid is its own: timed once, at the preset's default
        enc = build_encoder(name, preset, cells=f if name == "pointpillars" else None).eval()
        encoders[name] = enc
        inputs = enc.example_inputs()
        call = (lambda e=enc, x=inputs: e(x)) if name == "pointpillars" else (lambda e=enc, x=inputs: e(*x))
        rows.append({"preset": label, "kind": "encoder", "name": name, "agents": 1,
                     "params": _params(enc), "ms": _time_ms(call, repeats)})
    for name in FUSION:
        fus = build_fusion(name, preset).eval()
        for n in AGENTS:
            feats = torch.randn(1, n, p.channels, f, f).relu()
            valid = torch.ones(1, n, dtype=torch.bool)
            rows.append({"preset": label, "kind": "fusion", "name": name, "agents": n,
                         "params": _params(fus), "ms": _time_ms(lambda f=fus, x=feats, v=valid: f(x, v), repeats)})
    feats4 = torch.randn(1, 4, p.channels, f, f).relu()
    rows.append({"preset": label, "kind": "warp", "name": "warp_to_ego", "agents": 4, "params": 0,
                 "ms": _time_ms(lambda: warp_to_ego(feats4, _poses(4)), repeats)})
    for modality in ("camera", "lidar") if cells is None else ("lidar",):
        heads = build_heads(modality, preset, f if modality == "lidar" else None).eval()
        x = feats4[:, 0] if modality == "lidar" else torch.randn(1, p.channels, p.camera_cells, p.camera_cells)
        rows.append({"preset": label, "kind": "heads", "name": f"heads-{modality}", "agents": 1,
                     "params": _params(heads), "ms": _time_ms(lambda h=heads, x=x: h(x), repeats)})
    # Per-frame ego budget: its own PointPillars sweep (the other CAVs encode in their own processes)
    # + warp of the 4 maps + FuseBEVT.
    pp, fuse = encoders["pointpillars"], build_fusion("cobevt", preset).eval()
    sweep = pp.example_inputs()
    valid4 = torch.ones(1, 4, dtype=torch.bool)

    def frame() -> torch.Tensor:
        own = pp(sweep)  # [1, C, F, F]
        stack = torch.cat([own[:, None], feats4[:, 1:]], dim=1)
        warped, _ = warp_to_ego(stack, _poses(4))
        return fuse(warped, valid4)

    rows.append({"preset": label, "kind": "frame", "name": "pointpillars+warp+cobevt", "agents": 4,
                 "params": _params(pp) + _params(fuse), "ms": _time_ms(frame, repeats)})
    heads = build_heads("lidar", preset, f).eval()
    rows.append({"preset": label, "kind": "frame", "name": "pointpillars+warp+cobevt+heads", "agents": 4,
                 "params": _params(pp) + _params(fuse) + _params(heads),
                 "ms": _time_ms(lambda: heads(frame()), repeats)})
    return rows


def _train_step(fus: torch.nn.Module, heads: torch.nn.Module, feats: torch.Tensor, bf16: bool
                ) -> Callable[[], None]:
    """One AdamW step of fusion + heads on `feats` [B, L, C, F, F] (every agent present)."""
    params = [*fus.parameters(), *heads.parameters()]
    opt = torch.optim.AdamW(params, lr=1e-4)
    valid = torch.ones(feats.shape[:2], dtype=torch.bool)

    def step() -> None:
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            out = heads(fus(feats, valid))
        loss = sum(v.float().square().mean() for v in out.values())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step


def bench_train_steps(preset: str, cells: int | None, repeats: int) -> list[dict]:
    """Rows {preset, method, precision, ms}: one training step of each fusion stage's trainable part (fusion +
    LiDAR heads, batch 4 x 4 agents of cached-size features, forward + backward + AdamW) in float32 and under
    bfloat16 autocast, as `v2vsim train --bf16` runs it."""
    p = get_preset(preset)
    f = cells or p.cells
    rows = []
    for name in FUSION:
        torch.manual_seed(0)
        fus, heads = build_fusion(name, preset).train(), build_heads("lidar", preset, f).train()
        feats = torch.randn(4, 4, p.channels, f, f).relu()
        for precision in ("float32", "bfloat16"):
            step = _train_step(fus, heads, feats, precision == "bfloat16")
            times = []
            for i in range(repeats + 1):  # the first one warms up
                t = time.perf_counter()
                step()
                if i:
                    times.append((time.perf_counter() - t) * 1e3)
            rows.append({"preset": f"{preset} {f}x{f}", "method": name, "precision": precision,
                         "ms": statistics.median(times)})
    return rows


def format_train_rows(rows: list[dict]) -> str:
    out = ["| preset | method | float32 ms/step | bfloat16 ms/step | speed-up |", "|---|---|---:|---:|---:|"]
    by: dict[tuple[str, str], dict[str, float]] = {}
    for r in rows:
        by.setdefault((r["preset"], r["method"]), {})[r["precision"]] = r["ms"]
    for (preset, method), ms in by.items():
        out.append(f"| {preset} | {method} | {ms['float32']:.0f} | {ms['bfloat16']:.0f} | "
                   f"{ms['float32'] / ms['bfloat16']:.2f}x |")
    return "\n".join(out)


def format_rows(rows: list[dict]) -> str:
    """Markdown table: encoders/heads/frame one row each, fusion one row per method with N columns."""
    out = ["| preset | kind | name | params | ms (N=1) | ms (N=2) | ms (N=4) | ms (N=8) |",
           "|---|---|---|---:|---:|---:|---:|---:|"]
    seen: dict[tuple[str, str, str], dict[int, float]] = {}
    params: dict[tuple[str, str, str], int] = {}
    for r in rows:
        key = (r["preset"], r["kind"], r["name"])
        seen.setdefault(key, {})[r["agents"]] = r["ms"]
        params[key] = r["params"]
    for key, by_n in seen.items():
        if key[1] == "fusion":
            cells = [f"{by_n[n]:.2f}" for n in AGENTS]
        else:
            n, ms = next(iter(by_n.items()))
            cells = [f"{ms:.2f}" if n == a else "" for a in AGENTS]
        out.append(f"| {key[0]} | {key[1]} | {key[2]} | {params[key]:,} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="v2vsim bench models", description=__doc__.splitlines()[0])
    ap.add_argument("--presets", default="tiny,paper")
    ap.add_argument("--cells", default=None, metavar="F,F,...",
                    help="LiDAR fusion grids to time (e.g. 32,64,128; default: each preset's own)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--train-step", action="store_true",
                    help="instead: one training step of each fusion stage (fusion + heads, batch 4 x 4 agents) in "
                         "float32 and bfloat16 autocast")
    ap.add_argument("--json", default=None, help="also write the rows as JSON here")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    rows: list[dict] = []
    grids = [None] if args.cells is None else [int(c) for c in args.cells.split(",")]
    if args.train_step:
        rows = [r for preset in args.presets.split(",") for c in grids
                for r in bench_train_steps(preset, c, args.repeats)]
        print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), median of {args.repeats} steps")
        print(format_train_rows(rows))
        if args.json:
            with open(args.json, "w") as fh:
                json.dump(rows, fh, indent=1)
        return 0
    for preset in args.presets.split(","):
        for cells in grids:
            rows += bench_preset(preset, args.repeats, cells)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), median of {args.repeats}")
    print(format_rows(rows))
    for r in rows:
        if r["preset"].startswith("tiny ") and r["name"] == "pointpillars+warp+cobevt":
            print(f"\n{r['preset']}: PointPillars (32k points) + warp + FuseBEVT, 4 agents: {r['ms']:.1f} ms")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    return 0
