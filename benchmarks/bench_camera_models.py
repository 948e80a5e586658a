"""CPU benchmark of the camera encoders (SinBEVT, LaRa; per agent, 4 cameras) and FuseBEVT (N agents).

Prints parameter counts and single-thread forward latency (torch.set_num_threads(1), eval, no_grad)
for the "tiny" and "paper" presets. Encoders get one agent's 4 camera images at the simulator's raw size
(tiny 200x150, paper 800x600; resizing is part of the measured forward). FuseBEVT gets N stacked
C x 32 x 32 maps (C = 64 tiny, 128 paper), all agents present.

    python benchmarks/bench_camera_models.py [--presets tiny,paper] [--repeats-tiny 10] [--repeats-paper 2]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable

import torch
from torch import nn

from models.fusion.cobevt import FuseBEVT
from models.lara import build_lara
from models.sinbevt import build_sinbevt


def params(m: nn.Module) -> int:
    return sum(p.numel() for p in m.parameters())


def latency_ms(fn: Callable[[], object], repeats: int) -> float:
    """Median of ``repeats`` timed calls after one warm-up call."""
    with torch.no_grad():
        fn()
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def row(preset: str, model: str, inp: str, out: str, n_params: str | int, ms: str | float) -> str:
    n = f"{n_params:,}" if isinstance(n_params, int) else n_params
    t = f"{ms:.1f}" if isinstance(ms, float) else ms
    return f"{preset:<6} {model:<9} {inp:<24} {out:<14} {n:>11} {t:>9}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", default="tiny,paper")
    ap.add_argument("--repeats-tiny", type=int, default=10)
    ap.add_argument("--repeats-paper", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, load avg {os.getloadavg()[0]:.2f}")
    print(row("preset", "model", "input (per batch 1)", "output", "params", "ms"))
    for preset in args.presets.split(","):
        reps = args.repeats_paper if preset == "paper" else args.repeats_tiny
        for name, build in (("sinbevt", build_sinbevt), ("lara", build_lara)):
            m = build(preset).eval()
            inputs = m.example_inputs(batch=1)
            with torch.no_grad():
                out = m(*inputs)
            ms = latency_ms(lambda m=m, inputs=inputs: m(*inputs), reps)
            shape = "x".join(map(str, inputs[0].shape[1:]))
            print(row(preset, name, shape, "x".join(map(str, out.shape[1:])), params(m), ms))
        channels = 128 if preset == "paper" else 64
        fuse = FuseBEVT(channels, heads=4, window=8, blocks=3, mlp_dim=2 * channels, max_agents=8).eval()
        for n in (1, 2, 4, 8):
            x = torch.randn(1, n, channels, 32, 32)
            valid = torch.ones(1, n, dtype=torch.bool)
            ms = latency_ms(lambda fuse=fuse, x=x, valid=valid: fuse(x, valid), reps)
            print(row(preset, "fusebevt", f"N={n} x {channels}x32x32", f"{channels}x32x32", params(fuse), ms))


if __name__ == "__main__":
    main()
