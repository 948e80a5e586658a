"""Does a trusted sender say what the others see? The ego's misbehaviour check and defence (`defence`, issue 55;
docs/run.md "Threat model").

Signatures stop outsiders; they cannot stop an insider, a CAV with its genuine identity that sends false content
(v2vsim/comm/misbehaviour.py injects such lies on purpose). This module scores each sender's content against the
consensus of everyone else, in the spirit of CP-Guard's collaborative consistency (Hu et al., AAAI 2025): each agent's
single-agent maps (vehicle, road, lane probabilities: its features decoded alone by the `none` model, or late
fusion's outputs as sent) are warped into the ego grid with the pose it claims and judged two ways:

    road_vs_map(s) = mean |road_s - map| over the cells near s      the map is the drivable area of the HD map the
                     less the ego's own over the cells near it      ego plans on (map knowledge, not the frame's
                                                                    truth); a moved, turned, mirrored, scaled or
                                                                    zeroed map misplaces the road; an honest one is
                                                                    about as wrong as the ego's own model
    vehicle_m2(s)  = area of the cells near s and near another      a vehicle added or removed where others see
                     agent where |veh_s - veh_ref| > 0.5            the cell: veh_ref is the mean vehicle map of the
                                                                    other agents near the cell (the ego among them)

`near`: within `near_m` of the agent and on its grid. A sender is flagged at a frame when either exceeds its
threshold (DefenceConfig), calibrated on clean runs of tuning seeds; with fewer than `min_shared_m2` of shared
cells there is no evidence and nothing is flagged. A liar pulls the vehicle consensus too: the most disagreeing
flagged sender is left out of every reference and the others are judged again (check_frame), so an honest sender
is not flagged for disagreeing with a liar where only the two of them see. Also recorded, not judged by: `road`
and `road_corr`, the sender's road against the others' (on networks the road model never saw, honest agents'
road maps disagree with each other as much as a lie does: docs/results.md "A lying CAV"). What it cannot see, by
construction: a vehicle lie about cells no other agent is near (a vehicle hidden where only the liar sees).

The defence (`defence.exclude`) fuses every method without the senders flagged at that frame.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from models.heads import segmentation_probabilities
from models.warp import warp_to_ego
from v2vsim.config.schema_misbehaviour import DefenceConfig
from v2vsim.perception.device import model_device, to_host
from v2vsim.perception.encode import heads_float
from v2vsim.perception.fuse import FusionInputs
from v2vsim.perception.precision import Precision

VEHICLE, ROAD = 0, 1  # channels of a single-agent map [3, S, S]: vehicle, road, lane
MAX_CELLS = 128  # maps are compared on at most this grid (0.78 m cells over 100 m: a car spans ~6 x 2 cells)


@dataclass(frozen=True)
class Disagreement:
    """One sender's disagreement with the others at one frame (None: no shared cells to judge by)."""

    road: float | None
    vehicle_m2: float | None
    shared_m2: float
    road_corr: float | None = None  # Pearson correlation of the road maps over the shared cells (0: a flat map)
    # against the map the ego knows (its HD map's drivable area): the sender's mean |road - map| over the cells near
    # it, less the ego's own over the cells near the ego (how much worse than the ego's own road it is)
    road_vs_map: float | None = None

    def flagged(self, cfg: DefenceConfig) -> bool:
        """Past a threshold: its road worse against the map than the ego's own by road_threshold, or its vehicles
        unlike the others' on more than vehicle_threshold_m2."""
        if self.vehicle_m2 is None:
            return False
        road_bad = self.road_vs_map is not None and self.road_vs_map > cfg.road_limit(False)
        return road_bad or self.vehicle_m2 > cfg.vehicle_threshold_m2


@torch.no_grad()
def decode_alone(model: nn.Module, features: dict[str, np.ndarray], precision: Precision = "fp32"
                 ) -> dict[str, np.ndarray]:
    """Each sender's features [C, F, F] decoded alone by the single-agent model -> [3, S, S] probabilities
    (vehicle, road, lane) in the sender's own frame, one batch for every sender."""
    if not features:
        return {}
    names = list(features)
    device = model_device(model)
    feats = torch.from_numpy(np.stack([features[s] for s in names])).to(device)  # [L, C, F, F]
    out = heads_float(model, feats, precision, boxes=False)  # the maps are all the check reads
    probs = segmentation_probabilities(out["dynamic"], out["static"])  # each [L, S, S]
    maps = np.stack([to_host(probs[k]) for k in ("vehicle", "road", "lane")], axis=1)  # [L, 3, S, S]
    return {s: maps[i].astype(np.float32) for i, s in enumerate(names)}


@dataclass(frozen=True)
class _Warped:
    """One frame's single-agent maps in the ego grid, warped once for every round of check_frame."""

    names: list[str]  # the ego first
    warped: Tensor  # [L, 3, S, S]
    near: Tensor  # [L, S, S] 1.0 where the agent is within near_m of the cell and the cell is on its grid
    res: float  # metres per cell
    vs_map: list[float | None]  # per agent, road_vs_map (None without a map, or for an agent near no cell)


def _warp(maps: dict[str, np.ndarray], poses: dict[str, np.ndarray], ego: str, size_m: float, near_m: float,
          road_map: np.ndarray | None) -> _Warped | None:
    if ego not in maps or len(maps) < 2:
        return None
    names = [ego, *[s for s in maps if s != ego]]
    stack = torch.from_numpy(np.stack([maps[s] for s in names])).float()  # [L, 3, S, S]
    if stack.shape[-1] > MAX_CELLS:  # the warp's cost grows with S^2; the comparison needs no finer grid
        stack = F.adaptive_avg_pool2d(stack, MAX_CELLS)
    rel = torch.from_numpy(np.stack([np.asarray(poses[s], dtype=np.float32) for s in names]))  # [L, 3]
    warped, inside = warp_to_ego(stack, rel, size_m)  # [L, 3, S, S], [L, S, S]
    cells = stack.shape[-1]
    res = size_m / cells
    centre = size_m / 2 - (torch.arange(cells, dtype=torch.float32) + 0.5) * res
    fwd, left = centre[:, None], centre[None, :]  # a cell's (forward, left) in the ego frame, [S, 1] and [1, S]
    near = torch.stack([inside[i] & ((fwd - rel[i, 0]) ** 2 + (left - rel[i, 1]) ** 2 <= near_m ** 2)
                        for i in range(len(names))]).float()  # [L, S, S]
    vs_map: list[float | None] = [None] * len(names)
    if road_map is not None:  # [S', S'] bool, the ego grid: each agent's road against the map near it
        known = F.adaptive_avg_pool2d(torch.from_numpy(np.asarray(road_map, np.float32))[None, None], cells)[0, 0]
        err = [float((warped[i, ROAD] - known).abs()[near[i] > 0].mean()) if near[i].sum() > 0 else None
               for i in range(len(names))]
        if err[0] is not None:
            vs_map = [None if e is None else round(e - err[0], 4) for e in err]
    return _Warped(names, warped, near, res, vs_map)


def _score(g: _Warped, ignore: frozenset[str]) -> dict[str, Disagreement]:
    """Every sender's Disagreement with the mean of the other agents near each cell, `ignore`d ones left out of
    every reference (they are still scored)."""
    warped, near, res = g.warped, g.near, g.res
    voters = torch.tensor([s not in ignore for s in g.names], dtype=torch.float32)[:, None, None]  # [L, 1, 1]
    total_near = (near * voters).sum(0)  # [S, S]
    total_maps = (warped * (near * voters)[:, None]).sum(0)  # [3, S, S]
    out: dict[str, Disagreement] = {}
    for i, s in enumerate(g.names[1:], start=1):
        mine = near[i] * voters[i]
        others = total_near - mine
        shared = (near[i] > 0) & (others > 0)  # [S, S]
        shared_m2 = float(shared.sum()) * res * res
        if shared_m2 == 0:
            out[s] = Disagreement(None, None, 0.0, None, g.vs_map[i])
            continue
        ref = (total_maps - warped[i] * mine) / others.clamp(min=1)  # [3, S, S] mean of the others near
        diff = (warped[i] - ref).abs()
        road = float(diff[ROAD][shared].mean())
        vehicle_m2 = float((diff[VEHICLE][shared] > 0.5).sum()) * res * res
        a, b = warped[i, ROAD][shared], ref[ROAD][shared]
        a, b = a - a.mean(), b - b.mean()
        norm = float(a.norm() * b.norm())
        corr = float((a * b).sum()) / norm if norm > 1e-9 else 0.0
        out[s] = Disagreement(round(road, 4), round(vehicle_m2, 2), round(shared_m2, 1), round(corr, 4), g.vs_map[i])
    return out


def disagreements(maps: dict[str, np.ndarray], poses: dict[str, np.ndarray], ego: str, size_m: float,
                  near_m: float, ignore: frozenset[str] = frozenset(), road_map: np.ndarray | None = None
                  ) -> dict[str, Disagreement]:
    """Every sender's (not the ego's) Disagreement with the consensus of the others, `ignore`d senders left out
    of every reference (they are still scored).

    maps: sender -> [3, S, S] single-agent probabilities in its own frame (the ego's among them); poses: sender ->
    (dx, dy, dyaw) it claims in the ego's body frame. Row 0 of a grid is the front, column 0 the left; road_map:
    the drivable area of the ego's map on its own grid (None: no road_vs_map)."""
    g = _warp(maps, poses, ego, size_m, near_m, road_map)
    return {} if g is None else _score(g, ignore)


def judge(scores: dict[str, Disagreement], cfg: DefenceConfig) -> set[str]:
    """The senders flagged by these scores (enough shared cells and a score past its threshold)."""
    return {s for s, d in scores.items() if d.shared_m2 >= cfg.min_shared_m2 and d.flagged(cfg)}


def _excess(d: Disagreement, cfg: DefenceConfig) -> float:
    """How far past its thresholds a score is (> 1: flagged)."""
    return max((d.road_vs_map or 0.0) / max(cfg.road_limit(False), 1e-9),
               (d.vehicle_m2 or 0.0) / max(cfg.vehicle_threshold_m2, 1e-9))


def check_frame(maps: dict[str, np.ndarray], poses: dict[str, np.ndarray], ego: str, size_m: float,
                cfg: DefenceConfig, road_map: np.ndarray | None = None) -> tuple[dict[str, Disagreement], set[str]]:
    """One frame's verdict: each sender's scores and the senders flagged. A liar also pulls the consensus the
    honest senders are judged by, so the most disagreeing flagged sender is taken out of every reference and the
    rest judged again, until no one else is flagged (a greedy leave-one-out; the ego is never left out). A
    sender's scores are those of the last round it was judged in."""
    flagged: set[str] = set()
    g = _warp(maps, poses, ego, size_m, cfg.near_m, road_map)  # warped once; each round only re-scores
    if g is None:
        return {}, flagged
    scores = _score(g, frozenset())
    final = dict(scores)
    while True:
        suspects = judge({s: d for s, d in scores.items() if s not in flagged}, cfg)
        if not suspects:
            return final, flagged
        worst = max(suspects, key=lambda s: _excess(scores[s], cfg))
        flagged.add(worst)
        final[worst] = scores[worst]
        scores = _score(g, frozenset(flagged))
        final.update({s: d for s, d in scores.items() if s not in flagged})


def without(inp: FusionInputs, senders: set[str]) -> FusionInputs:
    """`inp` as if `senders` had sent nothing this frame (every kind, every method): the defence."""
    if not senders:
        return inp

    def keep(table: dict) -> dict:
        return {s: v for s, v in table.items() if s not in senders}

    return dataclasses.replace(
        inp, features=keep(inp.features), points=keep(inp.points), outputs=keep(inp.outputs),
        evidence=keep(inp.evidence),
        feature_ages=keep(inp.feature_ages), previous_features=keep(inp.previous_features),
        extrapolated={m: keep(t) for m, t in inp.extrapolated.items()})
