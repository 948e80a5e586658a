"""Learning what to share in v2vsim's PettingZoo env: a random policy, a confidence-threshold policy, and a
policy tuned by the cross-entropy method (CEM) to beat both on reward.

    python examples/share_policies.py [--scenario scenarios/intersection.yaml] [--train-seeds 30,31]
        [--eval-seeds 40,41] [--steps 15] [--iters 3] [--population 6] [--out share_policies.json]

Every CAV is an agent; its action is the share of its BEV feature cells to send (ranked by its own
confidence). Its reward is what its message added to the other CAVs' vehicle IoU (leave-one-out) minus
1e-6 per byte it encoded (v2vsim.env). The policies, all per agent and from the agent's own observation:

  random     a share drawn uniformly from [0, 1] each frame
  threshold  the share of its cells whose vehicle confidence is above 0.5 (Where2comm's selection rule)
  tuned      share = clip(base + scale * (share of cells above tau), 0, 1), and nothing when no other CAV is
             within `reach` metres; (base, tau, scale, reach) tuned by CEM on the training seeds

The tuned policy is scored on held-out seeds it never saw, beside the two fixed ones.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable

import numpy as np

from v2vsim.env import parallel_env

Policy = Callable[[dict, np.random.Generator], float]


def random_policy(obs: dict, rng: np.random.Generator) -> float:
    return float(rng.uniform())


def threshold_policy(obs: dict, rng: np.random.Generator, tau: float = 0.5) -> float:
    return float(np.mean(obs["confidence"] > tau))


def tuned_policy(theta: np.ndarray) -> Policy:
    base, tau, scale, reach = (float(v) for v in theta)

    def act(obs: dict, rng: np.random.Generator) -> float:
        d = obs["links"][:, 0]
        if not np.any((d >= 0) & (d <= reach)):
            return 0.0  # nobody near enough to gain from it: the bytes would be pure cost
        return float(np.clip(base + scale * np.mean(obs["confidence"] > tau), 0.0, 1.0))

    return act


def episode_reward(env, policy: Policy, seed: int, steps: int) -> dict:
    """Mean reward per agent-step over one episode, with the mean bytes and IoU gain behind it."""
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    rewards, sent, gains = [], [], []
    for _ in range(steps):
        if not env.agents:
            break
        actions = {a: np.array([policy(obs[a], rng)], np.float32) for a in env.agents}
        obs, rew, _, _, info = env.step(actions)
        rewards += list(rew.values())
        sent += [i["bytes"] for i in info.values()]
        gains += [i["iou_gain"] for i in info.values()]
    return {"reward": float(np.mean(rewards)), "bytes": float(np.mean(sent)), "iou_gain": float(np.mean(gains))}


def evaluate(env, policy: Policy, seeds: list[int], steps: int) -> dict:
    runs = [episode_reward(env, policy, s, steps) for s in seeds]
    return {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}


def _describe(theta: np.ndarray) -> str:
    return f"base {theta[0]:.3f}, tau {theta[1]:.2f}, scale {theta[2]:.2f}, reach {theta[3]:.0f} m"


def cem(env, seeds: list[int], steps: int, iters: int, population: int, log: Callable[[str], None]) -> np.ndarray:
    """Cross-entropy method over (base, tau, scale, reach): sample, keep the best third, refit a diagonal Gaussian."""
    rng = np.random.default_rng(0)
    mean, std = np.array([0.1, 0.5, 1.0, 70.0]), np.array([0.1, 0.25, 0.5, 25.0])
    lo, hi = np.array([0.0, 0.0, 0.0, 0.0]), np.array([1.0, 1.0, 4.0, 150.0])
    best, best_r = mean.copy(), -np.inf
    for it in range(iters):
        cands = np.clip(rng.normal(mean, std, size=(population, len(mean))), lo, hi)
        scores = np.array([evaluate(env, tuned_policy(c), seeds, steps)["reward"] for c in cands])
        elite = cands[np.argsort(scores)[-max(2, population // 3):]]
        mean, std = elite.mean(axis=0), elite.std(axis=0) + 1e-3
        if scores.max() > best_r:
            best_r, best = float(scores.max()), cands[int(np.argmax(scores))]
        log(f"CEM iteration {it + 1}/{iters}: best reward {scores.max():+.4f} ({_describe(best)}), "
            f"mean {scores.mean():+.4f}")
    return best


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", default="scenarios/intersection.yaml")
    p.add_argument("--train-seeds", default="30,31")
    p.add_argument("--eval-seeds", default="40,41")
    p.add_argument("--steps", type=int, default=15, help="steps per episode")
    p.add_argument("--iters", type=int, default=4)
    p.add_argument("--population", type=int, default=8)
    p.add_argument("--out", default=None, help="write the results as JSON here")
    a = p.parse_args()
    train = [int(s) for s in a.train_seeds.split(",")]
    held_out = [int(s) for s in a.eval_seeds.split(",")]
    t0 = time.monotonic()

    def log(msg: str) -> None:
        print(f"[{time.monotonic() - t0:6.0f} s] {msg}", flush=True)

    env = parallel_env(a.scenario, features="pooled")
    try:
        theta = cem(env, train, a.steps, a.iters, a.population, log)
        results = {name: evaluate(env, pol, held_out, a.steps) for name, pol in
                   (("random", random_policy), ("threshold", threshold_policy), ("tuned", tuned_policy(theta)))}
    finally:
        env.close()
    print(f"\nheld-out seeds {held_out}, {a.steps} steps each; per agent and step:")
    print(f"{'policy':10s} {'reward':>9s} {'IoU gain':>9s} {'bytes':>9s}")
    for name, r in results.items():
        print(f"{name:10s} {r['reward']:+9.4f} {r['iou_gain']:+9.4f} {r['bytes']:9.0f}")
    print(f"tuned: {_describe(theta)}")
    if a.out:
        with open(a.out, "w") as f:
            json.dump({"theta": theta.tolist(), "held_out": held_out, "train": train, "results": results}, f, indent=1)


if __name__ == "__main__":
    main()
