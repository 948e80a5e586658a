"""Benchmark the PettingZoo env (v2vsim.env): steps per second with the scenario's CAVs (4 by default).

    v2vsim bench env [--scenario intersection] [--steps 20] [--threads 2]
                                   [--json out.json]

Three configurations: the default (every CAV a receiver, leave-one-out reward, full feature maps), the
ego as the only receiver with leave-one-out, and the ego only with the byte-cost reward (what
`v2vsim bandwidth` runs). Each: one reset (not timed), then `--steps` steps with every CAV sending a
random share; the figure is steps / wall second, and the share of a step spent in sensing + encoding
(the observations) is printed beside it. Not a test: figures depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from v2vsim.env import parallel_env

CONFIGS = {
    "all receivers, leave-one-out": {"receivers": "all"},
    "ego receiver, leave-one-out": {"receivers": "egos"},
    "ego receiver, byte cost only": {"receivers": "egos", "reward": "bytes"},
}


def bench(scenario: str, steps: int, kwargs: dict) -> dict:
    env = parallel_env(scenario, **kwargs)
    rng = np.random.default_rng(0)
    try:
        env.reset(seed=3)
        sense_s = 0.0
        original = env._sense

        def timed(*a: object, **k: object) -> object:
            nonlocal sense_s
            t = time.perf_counter()
            out = original(*a, **k)
            sense_s += time.perf_counter() - t
            return out

        env._sense = timed  # type: ignore[method-assign]
        t0 = time.perf_counter()
        n = 0
        for _ in range(steps):
            if not env.agents:
                break
            env.step({a: rng.uniform(0, 1, 1).astype(np.float32) for a in env.agents})
            n += 1
        wall = time.perf_counter() - t0
        return {"steps": n, "agents": len(env.possible_agents), "steps_per_s": round(n / wall, 3),
                "ms_per_step": round(1000 * wall / max(n, 1), 1), "sense_encode_share": round(sense_s / wall, 3)}
    finally:
        env.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="v2vsim bench env", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", default="intersection")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--threads", type=int, default=2, help="torch intra-op threads (the env is one process)")
    p.add_argument("--json", default=None)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    results = {}
    for name, kwargs in CONFIGS.items():
        r = results[name] = bench(a.scenario, a.steps, kwargs)
        print(f"{name:32s} {r['steps_per_s']:6.2f} steps/s  {r['ms_per_step']:7.1f} ms/step  "
              f"sensing+encoding {100 * r['sense_encode_share']:.0f} %  ({r['agents']} agents, {r['steps']} steps, "
              f"{a.threads} threads)", flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(results, f, indent=1)
    return 0
