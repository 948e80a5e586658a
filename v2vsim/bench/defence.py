"""What the ego's misbehaviour check costs a frame (`defence`, agents/ego_defence.py), whole and by part.

    v2vsim bench defence [--scenario scenarios/t_junction_occluded.yaml] [--senders 4] [--repeats 20]
                         [--threads 1] [--set key=value ...]

Builds the scenario's single-agent (`none`) model from its zoo and one frame of inputs at the run's sizes (every
sender's feature map, its free-space evidence, its claimed pose; random values: a convolution's cost does not depend
on them), then times, median over `--repeats` after two warm-up calls: the whole check with `defence.detect` and
with `defence.evidence`, and its parts (the senders' maps decoded alone, the consistency comparison, the evidence's
claims, the pose against the map, the ego's later view). The ego's own map comes from its `none` prediction, as in a
run (agents/ego.py), so the decode is of the other senders. Compare versions side by side in one session, on one
machine (docs/results.md gives the figures measured).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
import torch


def _median_ms(fn: Callable[[], object], repeats: int) -> float:
    for _ in range(2):
        fn()
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t) * 1000)
    return float(np.median(out))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="v2vsim bench defence", description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="scenarios/t_junction_occluded.yaml")
    ap.add_argument("--senders", type=int, default=4, help="agents in the frame, the ego among them (default 4)")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1, help="torch threads (a run's ego: 1)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    a = ap.parse_args(argv)
    if a.senders < 2:
        ap.error("--senders: at least 2 (the ego and one sender to check)")
    torch.set_num_threads(a.threads)

    from agents.ego_defence import SenderCheck
    from v2vsim.config.load import load_scenario
    from v2vsim.perception.build import build_agent_encoder, build_method_models
    from v2vsim.perception.consistency import MAX_CELLS, check_frame, decode_alone
    from v2vsim.perception.evidence import evidence_cells
    from v2vsim.perception.evidence_check import judge_claims, on_ego_grid, pose_check, wall_outlines
    from v2vsim.perception.fuse import FusionInputs, predict
    from v2vsim.perception.plan import plan_models

    detect = load_scenario(a.scenario, ["defence.detect=true", *a.sets])
    evidence = load_scenario(a.scenario, ["defence.evidence=true", *a.sets])
    plan = plan_models(evidence)
    model = build_method_models(plan, build_agent_encoder(plan), ("none",))["none"].eval()
    rng = np.random.default_rng(0)
    names = [f"cav{i}" for i in range(a.senders)]
    c, f = model.heads.decoder.stages[0][1].in_channels, model.heads.in_cells
    feats = {s: rng.standard_normal((c, f, f)).astype(np.float32) for s in names}
    e = evidence_cells(f)
    ev = {s: rng.integers(0, 3, (e, e)).astype(np.uint8) for s in names}
    poses = np.array([[0.0, 0.0, 0.0]] + [[rng.uniform(-30, 30), rng.uniform(-30, 30), rng.uniform(-np.pi, np.pi)]
                                          for _ in names[1:]], np.float32)
    inp = FusionInputs(senders=names, rel_poses=poses, features=feats, evidence=ev)
    size, cells = evidence.bev.size_m, evidence.bev.cells
    road = np.zeros((cells, cells), bool)
    road[:, cells // 2 - 8: cells // 2 + 8] = True
    buildings = np.zeros((MAX_CELLS, MAX_CELLS), bool)
    buildings[10:50, 10:50] = buildings[80:120, 80:120] = True
    with torch.no_grad():
        own = predict("none", model, inp, cells)
        frame = [0]

        def whole(sc: object) -> Callable[[], object]:
            check = SenderCheck(sc, model)  # type: ignore[arg-type]

            def run() -> object:
                frame[0] += 1
                return check.check(frame[0], inp, road, buildings, (float(frame[0]), 0.0, 0.0), own)
            return run

        others = {s: x for s, x in feats.items() if s != names[0]}
        maps = decode_alone(model, feats)
        vehicle = {s: m[0] for s, m in maps.items()}
        rel = {s: poses[i] for i, s in enumerate(names)}
        grid = on_ego_grid(vehicle, ev, rel, size, MAX_CELLS)
        outlines = wall_outlines(buildings)
        rows = [
            ("the whole check, defence.detect", _median_ms(whole(detect), a.repeats)),
            ("the whole check, defence.evidence", _median_ms(whole(evidence), a.repeats)),
            (f"  the {a.senders - 1} senders' maps decoded alone", _median_ms(lambda: decode_alone(model, others),
                                                                           a.repeats)),
            ("  the consistency comparison", _median_ms(
                lambda: check_frame(maps, rel, names[0], size, detect.defence, road), a.repeats)),
            ("  the evidence on the ego grid and the claims", _median_ms(
                lambda: judge_claims(on_ego_grid(vehicle, ev, rel, size, MAX_CELLS), size, None), a.repeats)),
            ("  the senders' poses against the map", _median_ms(
                lambda: [pose_check(ev[s], rel[s], buildings, size, outlines) for s in names[1:]], a.repeats)),
        ]
    assert grid is not None
    print(f"v2vsim bench defence: {a.scenario}, {a.senders} agents, {a.threads} thread(s), median of {a.repeats}\n")
    print("| part | ms a frame |\n|---|---|")
    for name, ms in rows:
        print(f"| {name} | {ms:.1f} |")
    return 0
