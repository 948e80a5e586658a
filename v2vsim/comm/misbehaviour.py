"""A CAV that lies on purpose (`misbehaviour`, issue 55; docs/run.md "Threat model"): a trusted sender, holding its
genuine identity, that sends false content. Each lie is a pure function of what the CAV would have sent honestly;
the agent applies the lies active at a frame just before it sends (its own perception stays honest).

Lies (`Lie.kind`), on the intermediate features [C, F, F] (the sender's BEV, row 0 = front, column 0 = left, over
bev.size_m), on late fusion's outputs (probabilities [3, S, S]: vehicle, road, lane; boxes [K, 6]: x, y, l, w, yaw,
score in its body frame) and on the pose every message claims:

    scale           features x factor (a negative factor flips their sign); outputs unchanged
    flip            features and outputs mirrored left-right (what is on its left is sent as on its right)
    zero            features all 0; no vehicle, road or lane in its outputs, no boxes
    pose            the claimed pose moved by shift_m (forward, left, in its own frame) and turned by rotate_deg:
                    every message it sends (features, outputs, points) is placed there by the receivers
    remove_vehicle  the cells under each target vehicle (its footprint plus MARGIN_M) set to the map's background
                    (the per-channel median over the cells under no vehicle), its vehicle probability to 0 there and
                    its boxes dropped: the attack that hides the foe
    add_vehicle     a car that is not there (CAR_LM x CAR_WM, heading as the sender's) at at_m in its frame: its
                    cells set to the mean feature of the cells under the vehicles it truly sees, vehicle
                    probability 1 there, a box with score 0.9; skipped (counted) on a frame where it sees none

Early fusion's points lie only in the pose (a point-level lie is not built).

The free-space evidence (defence.evidence) stays honest unless the lie says `evidence: consistent`: an attacker
that knows the defence makes its rays agree with its claims. flip mirrors the evidence; zero makes it all unknown;
remove_vehicle marks the hidden cells unknown (as if it never saw there: "free" would contradict anyone who sees
the car, "occupied" its own empty map); add_vehicle marks the phantom's cells occupied; scale and pose leave it
as it is (its claims are in its own frame either way).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from v2vsim.config.schema_misbehaviour import Lie
from v2vsim.evaluation.gt import rasterise_boxes
from v2vsim.perception.evidence import OCCUPIED, UNKNOWN
from v2vsim.world.geometry import BevGrid, Pose, body_to_world, world_to_body, wrap_angle

MARGIN_M = 1.0  # a removed vehicle's footprint is grown by this on every side: its features spread past its body
CAR_LM, CAR_WM = 4.5, 1.9  # an added vehicle's footprint
ADDED_SCORE = 0.9


@dataclass(frozen=True)
class Sent:
    """What a CAV sends at one frame, honest or not."""

    features: np.ndarray  # [C, F, F]
    pose: tuple[float, float, float, float]  # x, y, z, yaw (world)
    maps: np.ndarray | None = None  # late fusion's [3, S, S]
    boxes: np.ndarray | None = None  # late fusion's [K, 6]
    evidence: np.ndarray | None = None  # defence.evidence: its rays' [F, F] UNKNOWN / FREE / OCCUPIED


def describe(lie: Lie) -> str:
    """One lie in words, for the terminal, the report and the recording."""
    what = {"scale": f"features x {lie.factor:g}", "flip": "features and outputs mirrored left-right",
            "zero": "all-zero features and outputs",
            "pose": (f"pose moved {lie.shift_m[0]:g} m forward, {lie.shift_m[1]:g} m left, turned "
                     f"{lie.rotate_deg:g} deg"),
            "remove_vehicle": f"hides {', '.join(lie.targets)}",
            "add_vehicle": f"adds a car at {lie.at_m[0]:g} m forward, {lie.at_m[1]:g} m left"}[lie.kind]
    return f"{', '.join(lie.cavs)}: {lie.kind} ({what}) from frame {lie.from_frame}"


def liars(lies: Sequence[Lie]) -> dict[str, str]:
    """CAV id -> the kinds it tells (the recording's label)."""
    out: dict[str, list[str]] = {}
    for lie in lies:
        for c in lie.cavs:
            out.setdefault(c, []).append(lie.kind)
    return {c: "+".join(k) for c, k in out.items()}


def active(lies: Sequence[Lie], me: str, frame: int) -> list[Lie]:
    """The lies CAV `me` tells at `frame`, in the order the scenario lists them."""
    return [lie for lie in lies if me in lie.cavs and frame >= lie.from_frame]


def claimed_pose(pose: tuple[float, float, float, float], lie: Lie) -> tuple[float, float, float, float]:
    """The pose a `pose` lie claims: moved by shift_m in the sender's own frame, turned by rotate_deg."""
    x, y, z, yaw = pose
    moved = body_to_world(np.asarray(lie.shift_m, dtype=np.float64), Pose(x, y, z, yaw))
    return (float(moved[0]), float(moved[1]), z, float(wrap_angle(yaw + math.radians(lie.rotate_deg))))


def _mask(boxes: np.ndarray, size_m: float, cells: int, margin: float = 0.0) -> np.ndarray:
    """[cells, cells] bool: cells under any of `boxes` (K, >=5: x, y, l, w, yaw in the sender's frame)."""
    if len(boxes) == 0:
        return np.zeros((cells, cells), dtype=bool)
    grown = np.asarray(boxes[:, :5], dtype=np.float64).copy()
    grown[:, 2:4] += 2 * margin
    return rasterise_boxes(grown, BevGrid(size_m, cells))


def _inside(points: np.ndarray, boxes: np.ndarray, margin: float) -> np.ndarray:
    """[N] bool: box centres (N, >=2) inside any of `boxes` grown by margin."""
    out = np.zeros(len(points), dtype=bool)
    for x, y, length, width, yaw in np.asarray(boxes[:, :5], dtype=np.float64):
        local = world_to_body(np.asarray(points[:, :2], dtype=np.float64), Pose(x, y, 0.0, yaw))
        out |= (np.abs(local[:, 0]) <= length / 2 + margin) & (np.abs(local[:, 1]) <= width / 2 + margin)
    return out


def apply(sent: Sent, lie: Lie, size_m: float, targets: np.ndarray, seen: np.ndarray) -> tuple[Sent, bool]:
    """`sent` after one lie, and whether it was told; its evidence made to agree when the lie says so (module
    doc)."""
    out, told = _apply(sent, lie, size_m, targets, seen)
    if not told or lie.evidence != "consistent" or sent.evidence is None:
        return dataclasses.replace(out, evidence=sent.evidence), told
    return dataclasses.replace(out, evidence=_consistent(sent.evidence, lie, size_m, targets)), told


def _consistent(ev: np.ndarray, lie: Lie, size_m: float, targets: np.ndarray) -> np.ndarray:
    """The evidence [F, F] that agrees with what `lie` claims (module doc)."""
    n = ev.shape[-1]
    if lie.kind == "flip":
        return ev[:, ::-1].copy()
    if lie.kind == "zero":
        return np.full_like(ev, UNKNOWN)
    out = ev.copy()
    if lie.kind == "remove_vehicle":
        out[_mask(targets, size_m, n, MARGIN_M)] = UNKNOWN
    elif lie.kind == "add_vehicle":
        out[_mask(np.array([[lie.at_m[0], lie.at_m[1], CAR_LM, CAR_WM, 0.0]]), size_m, n)] = OCCUPIED
    return out


def _apply(sent: Sent, lie: Lie, size_m: float, targets: np.ndarray, seen: np.ndarray) -> tuple[Sent, bool]:
    """`sent` after one lie, and whether it was told (add_vehicle needs a vehicle it sees to copy).

    targets: (K, 5) the footprints of lie.targets in the sender's frame (remove_vehicle); seen: (K, 5) those of the
    vehicles it truly sees (add_vehicle's feature template)."""
    f = sent.features
    c, n, _ = f.shape
    maps, boxes = sent.maps, sent.boxes
    if lie.kind == "scale":
        return Sent((f.astype(np.float32) * lie.factor).astype(f.dtype), sent.pose, maps, boxes), True
    if lie.kind == "flip":
        fb = None if boxes is None else boxes.copy()
        if fb is not None:
            fb[:, 1], fb[:, 4] = -fb[:, 1], -fb[:, 4]
        return Sent(f[:, :, ::-1].copy(), sent.pose, None if maps is None else maps[:, :, ::-1].copy(), fb), True
    if lie.kind == "zero":
        return Sent(np.zeros_like(f), sent.pose, None if maps is None else np.zeros_like(maps),
                    None if boxes is None else boxes[:0].copy()), True
    if lie.kind == "pose":
        return Sent(f, claimed_pose(sent.pose, lie), maps, boxes), True
    if lie.kind == "remove_vehicle":
        hide = _mask(targets, size_m, n, MARGIN_M)
        if not hide.any():
            return sent, False
        background = np.median(f[:, ~hide].astype(np.float32), axis=1) if (~hide).any() else np.zeros(c)
        out = f.copy()
        out[:, hide] = background.astype(f.dtype)[:, None]
        m = None
        if maps is not None:
            m = maps.copy()
            m[0][_mask(targets, size_m, m.shape[-1], MARGIN_M)] = 0.0
        b = None if boxes is None else boxes[~_inside(boxes[:, :2], targets, MARGIN_M)].copy()
        return Sent(out, sent.pose, m, b), True
    if lie.kind == "add_vehicle":
        under = _mask(seen, size_m, n)
        if not under.any():
            return sent, False
        phantom = np.array([[lie.at_m[0], lie.at_m[1], CAR_LM, CAR_WM, 0.0]])
        cells = _mask(phantom, size_m, n)
        out = f.copy()
        out[:, cells] = f[:, under].astype(np.float32).mean(axis=1).astype(f.dtype)[:, None]
        m = None
        if maps is not None:
            m = maps.copy()
            m[0][_mask(phantom, size_m, m.shape[-1])] = 1.0
        b = None
        if boxes is not None:
            b = np.concatenate([boxes, np.array([[*phantom[0], ADDED_SCORE]], dtype=boxes.dtype)])
        return Sent(out, sent.pose, m, b), True
    raise ValueError(f"unknown lie {lie.kind!r}")


def tell(sent: Sent, lies: Sequence[Lie], size_m: float, targets: dict[str, np.ndarray],
         seen: np.ndarray) -> tuple[Sent, list[str]]:
    """Every lie in turn; the kinds told (a lie that could not be told this frame is left out).
    targets: actor id -> its (5,) footprint in the sender's frame (the actors on its grid)."""
    told = []
    for lie in lies:
        mine = np.array([targets[t] for t in lie.targets if t in targets]).reshape(-1, 5)
        sent, ok = apply(sent, lie, size_m, mine, seen)
        if ok:
            told.append(lie.kind)
    return sent, told
