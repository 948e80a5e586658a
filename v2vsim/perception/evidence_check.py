"""Claims against rays: each sender's vehicle map judged by the free-space evidence the agents send (issue 67 item 2).

Collaborative Anomaly Detection's two checks (Zhang et al., USENIX Security 2024, Sec. 6), on the ego grid, with
every agent's evidence (v2vsim/perception/evidence.py: occupied / free / unknown per cell from its own rays) and its
single-agent vehicle map (its features decoded alone, as the consistency check decodes them) warped there by the
pose it claims:

    phantom_m2(s) = area where s claims a vehicle (p > 0.5), another agent's rays passed (free, away from any
                    hit) and no other agent's rays were stopped (occupied): spoofing, a car put where others see
                    through
    removed_m2(s) = area where another agent sees a vehicle (its map p > 0.5 and its rays stopped there) and s's
                    own rays reached the cell (free or occupied) but s claims nothing there (p < 0.25): removal
    unclaimed_m2(s) = area of the drivable map where s's own rays were stopped and s claims nothing (p < 0.25):
                    removal that no one else can see, told by the liar's own evidence against its own map

And the pose it claims (pose_check), against the map rather than anyone's word: the cells where its rays were
stopped, placed by the claimed pose, should fall on the outlines of the HD map's buildings where they are walls.
The correction (a rotation about the sender, then a shift) that puts most of them on the outlines is searched over
+-POSE_SHIFT_CELLS x POSE_TURNS_DEG; an honest pose needs none, a pose told 2 m off needs about 2 m. The map is always
there, so the check needs no other agent and no shared area.

Never one agent's evidence for its own claims: phantom and removed ask the others, and unclaimed can only convict
(a liar that lies in its evidence too, consistently, escapes it, and is caught only where another agent sees;
a lie about a place only the liar sees cannot be caught by anyone). The ego is one of the "others" for each
sender. Thresholds and their calibration: DefenceConfig (`defence.phantom_m2`, ...).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from models.warp import warp_to_ego
from v2vsim.perception.evidence import FREE, OCCUPIED
from v2vsim.world.geometry import Pose, relative_pose

CLAIM, NO_CLAIM = 0.5, 0.25  # a vehicle claimed above CLAIM; nothing claimed below NO_CLAIM (between: unsure)
POSE_SHIFT_CELLS = 5  # the correction's shift is searched over +-5 cells (+-3.9 m at 0.78 m) on each axis ...
POSE_TURNS_DEG = (-8.0, -6.0, -4.0, -2.0, 0.0, 2.0, 4.0, 6.0, 8.0)  # ... at each of these turns about the sender


@dataclass(frozen=True)
class EvidenceVerdict:
    """One sender's claims against the agents' rays at one frame (areas in m^2)."""

    phantom_m2: float
    removed_m2: float
    unclaimed_m2: float
    witnessed_m2: float  # its claimed vehicle area that another agent's rays reached (how much could be checked)


def _planes(evidence: np.ndarray, cells: int) -> torch.Tensor:
    """[F, F] uint8 evidence -> [3, G, G] float (clear, free, occupied) at the comparison grid, nearest cells.
    Clear: free with the 3 x 3 cells around free too (a ray's last free cell can reach into the car it then hit, an
    evidence cell being 1.56 m, and an honest map's blur would count there as a phantom)."""
    ev = torch.from_numpy(np.asarray(evidence))
    free = (ev == FREE).float()[None, None]  # [1, 1, F, F]
    clear = 1.0 - F.max_pool2d(1.0 - free, 3, stride=1, padding=1)  # free eroded by one cell
    planes = torch.cat([clear[0], free[0], (ev == OCCUPIED).float()[None]])[None]  # [1, 3, F, F]
    return F.interpolate(planes, size=(cells, cells), mode="nearest")[0]


@dataclass(frozen=True)
class EgoGridEvidence:
    """Every agent's claims and rays warped onto the ego grid at one frame by the poses they claim (plain tensors,
    [L, G, G] each, agents in `names` order): what the checks below read."""

    names: list[str]
    vehicle: torch.Tensor  # float, its vehicle probability
    clear: torch.Tensor  # bool, free with the cells around free too (_planes)
    free: torch.Tensor  # bool
    occupied: torch.Tensor  # bool


def on_ego_grid(vehicle: dict[str, np.ndarray], evidence: dict[str, np.ndarray], poses: dict[str, np.ndarray],
                size_m: float, cells: int) -> EgoGridEvidence | None:
    """vehicle: agent -> [S, S] vehicle probability in its own frame; evidence: agent -> [F, F] uint8 in its own
    frame; poses: agent -> (dx, dy, dyaw) it claims in the ego frame (the ego (0, 0, 0)); cells: the grid G. None
    when no agent has both a vehicle map and evidence."""
    names = [s for s in vehicle if s in evidence and s in poses]
    if not names:
        return None
    veh = torch.from_numpy(np.stack([np.asarray(vehicle[s], np.float32) for s in names]))[:, None]  # [L, 1, S, S]
    if veh.shape[-1] != cells:
        veh = F.adaptive_avg_pool2d(veh, cells)
    ev = torch.stack([_planes(evidence[s], cells) for s in names])  # [L, 3, G, G]
    rel = torch.from_numpy(np.stack([np.asarray(poses[s], np.float32) for s in names]))  # [L, 3]
    v, _ = warp_to_ego(veh, rel, size_m)  # [L, 1, G, G]
    e, _ = warp_to_ego(ev, rel, size_m, mode="nearest")  # [L, 3, G, G]
    return EgoGridEvidence(names, v[:, 0], e[:, 0] > 0.5, e[:, 1] > 0.5, e[:, 2] > 0.5)


def road_on_grid(road_map: np.ndarray, cells: int) -> torch.Tensor:
    """The drivable area (bool, any size) on the comparison grid: [G, G] bool."""
    rm = torch.from_numpy(np.asarray(road_map, np.float32))[None, None]
    return F.adaptive_avg_pool2d(rm, cells)[0, 0] > 0.5


def check_evidence(vehicle: dict[str, np.ndarray], evidence: dict[str, np.ndarray], poses: dict[str, np.ndarray],
                   size_m: float, cells: int, road_map: np.ndarray | None = None) -> dict[str, EvidenceVerdict]:
    """Per agent with both a vehicle map and evidence: its verdict against every other such agent (arguments as
    on_ego_grid's; road_map: the drivable area of the ego's HD map on its grid, bool, any size; None: no
    unclaimed)."""
    grid = on_ego_grid(vehicle, evidence, poses, size_m, cells)
    road = None if road_map is None else road_on_grid(road_map, cells)
    return {} if grid is None else judge_claims(grid, size_m, road)


def judge_claims(grid: EgoGridEvidence, size_m: float, road: torch.Tensor | None,
                 ignore: frozenset[str] = frozenset()) -> dict[str, EvidenceVerdict]:
    """check_evidence on evidence already on the ego grid (road: [G, G] bool or None); `ignore`d agents are left
    out of every other agent's witnesses (a caught liar's claims and rays must not incriminate the honest) and
    themselves still judged."""
    names, v, clear, free, occ = grid.names, grid.vehicle, grid.clear, grid.free, grid.occupied
    seen = occ & (v > CLAIM)  # a vehicle an agent both maps and stops its rays on
    cell_m2 = (size_m / v.shape[-1]) ** 2
    out: dict[str, EvidenceVerdict] = {}
    for i, s in enumerate(names):
        others = [j for j in range(len(names)) if j != i and names[j] not in ignore]
        if not others:
            continue
        o_clear, o_occ, o_seen = clear[others].any(0), occ[others].any(0), seen[others].any(0)
        claim, none = v[i] > CLAIM, v[i] < NO_CLAIM
        reached = free[i] | occ[i]
        phantom = claim & o_clear & ~o_occ
        removed = o_seen & reached & none
        unclaimed = (occ[i] & none & road) if road is not None else torch.zeros_like(claim)
        out[s] = EvidenceVerdict(round(float(phantom.sum()) * cell_m2, 2), round(float(removed.sum()) * cell_m2, 2),
                                 round(float(unclaimed.sum()) * cell_m2, 2),
                                 round(float((claim & (free[others].any(0) | o_occ)).sum()) * cell_m2, 2))
    return out


@dataclass(frozen=True)
class PoseVerdict:
    """A sender's claimed pose against the map: the correction that best puts its walls on the map's buildings."""

    shift_m: float  # the correction's length
    turn_deg: float
    on_map: float  # the share of its hits on a building's outline (a cell either side) as claimed
    on_map_corrected: float  # ... after the correction
    hits: int  # the hits it was judged on (cells where its rays stopped)


def wall_outlines(buildings: np.ndarray) -> torch.Tensor:
    """The buildings' outlines, a cell either side (where a wall's hits fall): [E, E] float from [E, E] bool."""
    b = torch.from_numpy(np.asarray(buildings, np.float32))[None, None]
    grown, shrunk = F.max_pool2d(b, 3, stride=1, padding=1), -F.max_pool2d(-b, 3, stride=1, padding=1)
    return (grown - shrunk)[0, 0]


def pose_check(evidence: np.ndarray, pose: np.ndarray, buildings: np.ndarray, size_m: float,
               outlines: torch.Tensor | None = None) -> PoseVerdict | None:
    """evidence: the sender's [E, E] grid in its own frame; pose: its claimed (dx, dy, dyaw) in the ego frame;
    buildings: the HD map's building footprints on the ego grid ([E, E] bool, the same extent); outlines: their
    wall_outlines, where the caller judges several senders on one map. None when its rays hit no building cell
    under any correction (nothing to judge by)."""
    cells = buildings.shape[-1]
    occ = torch.from_numpy(np.asarray(evidence) == OCCUPIED).float()
    if occ.shape[-1] != cells:
        occ = F.interpolate(occ[None, None], size=(cells, cells), mode="nearest")[0, 0]
    hits = int(occ.sum())
    if hits == 0:
        return None
    rel = torch.tensor(np.asarray(pose, np.float32)).repeat(len(POSE_TURNS_DEG), 1)  # [T, 3]
    rel[:, 2] += torch.deg2rad(torch.tensor(POSE_TURNS_DEG))
    turned, _ = warp_to_ego(occ[None, None].expand(len(POSE_TURNS_DEG), 1, cells, cells).contiguous(), rel, size_m,
                            mode="nearest")  # [T, 1, G, G]
    walls = wall_outlines(buildings) if outlines is None else outlines
    # circular cross-correlation of each turned hit map with the grown buildings: score[t, i, j] = hits on a
    # building after shifting by (i, j) cells (rows forward, columns left); shifts past +-POSE_SHIFT_CELLS ignored
    score = torch.fft.irfft2(torch.fft.rfft2(walls)[None] * torch.conj(torch.fft.rfft2(turned[:, 0])), s=(cells, cells))
    n = POSE_SHIFT_CELLS
    score = torch.roll(score, shifts=(n, n), dims=(1, 2))[:, : 2 * n + 1, : 2 * n + 1]  # [T, 2n+1, 2n+1]
    kept = float(turned.sum() / len(POSE_TURNS_DEG))  # hits that land on the ego grid at all
    top = float(score.max())
    if top < 0.5 or kept < 1:
        return None
    # a wall's hits fit as well anywhere along the wall: of the corrections that fit (nearly) best, the least
    turns = torch.tensor(POSE_TURNS_DEG)[:, None, None] / 2.0  # a 2-degree turn costs as much as a cell's shift
    ax = torch.arange(-n, n + 1, dtype=torch.float32)
    cost = turns ** 2 + ax[None, :, None] ** 2 + ax[None, None, :] ** 2  # [T, 2n+1, 2n+1]
    cost = torch.where(score >= top - max(1.0, 0.02 * kept), cost, torch.full_like(cost, float("inf")))
    best = int(torch.argmin(cost))
    t, i, j = best // (2 * n + 1) ** 2, (best // (2 * n + 1)) % (2 * n + 1) - n, best % (2 * n + 1) - n
    zero = float(score[POSE_TURNS_DEG.index(0.0), n, n])
    res = size_m / cells
    return PoseVerdict(round(float(np.hypot(i, j)) * res, 2), POSE_TURNS_DEG[t], round(zero / kept, 3),
                       round(float(score[t, i + n, j + n]) / kept, 3), hits)


# The ego's own later view (issue 67 item 2): what a sender claimed about a place is checked when the ego's own
# rays reach it a few frames later. Vehicles move, so a claim is judged against every place the vehicle could have
# reached since, a square of half-width reach_m (speed x time) around it, on the road only (cars keep to it):
#
#   later_phantom_m2(s)  = area s claimed a vehicle at then where every road cell within reach is now clear to the
#                          ego's rays (the car it claimed cannot be anywhere now)
#   later_removed_m2(s)  = area of a vehicle the ego now sees (its map p > 0.5 and its rays stopped) where s then
#                          vouched every road cell within reach empty (its rays reached, it claimed nothing)
#
# The ego's own body is never clear in its own evidence, nor a sender's in its own (their rays start inside them).
FOOTPRINT_M = 3.0  # an agent's own body: this far around its origin is never vouched for by its own rays


@dataclass(frozen=True)
class LaterClaim:
    """What one sender told about the ego grid at one frame, kept for the ego's later view (on the ego grid then)."""

    frame: int
    ego_x: float  # the ego's world pose then
    ego_y: float
    ego_yaw: float
    claimed: torch.Tensor  # [G, G] bool: it claimed a vehicle
    empty: torch.Tensor  # [G, G] bool: its rays reached and it claimed nothing (its own body aside)


@dataclass(frozen=True)
class LaterVerdict:
    """A sender's claims of `frame` against the ego's own rays now (areas in m^2)."""

    frame: int  # the frame of the claims judged
    phantom_m2: float
    removed_m2: float


def _near(cells: int, size_m: float, xy: tuple[float, float], radius_m: float) -> torch.Tensor:
    """[G, G] bool: the cells whose centres lie within radius_m of the ego-frame point xy (rows forward, columns
    left, as models/warp.py lays the grid out)."""
    res = size_m / cells
    centre = size_m / 2 - (torch.arange(cells, dtype=torch.float32) + 0.5) * res  # x of row i, y of column j
    return (centre[:, None] - xy[0]) ** 2 + (centre[None, :] - xy[1]) ** 2 <= radius_m ** 2


def later_claims(grid: EgoGridEvidence, poses: dict[str, np.ndarray], frame: int,
                 ego_pose: tuple[float, float, float], size_m: float) -> dict[str, LaterClaim]:
    """Each sender's claims on this frame's ego grid, to be judged when the ego's rays reach them (the ego, first
    in grid.names, is judged by no one). ego_pose: the ego's world (x, y, yaw) now."""
    cells = grid.vehicle.shape[-1]
    out = {}
    for i, s in enumerate(grid.names[1:], start=1):
        body = _near(cells, size_m, (float(poses[s][0]), float(poses[s][1])), FOOTPRINT_M)
        reached = grid.free[i] | grid.occupied[i]
        out[s] = LaterClaim(frame, *ego_pose, grid.vehicle[i] > CLAIM, reached & (grid.vehicle[i] < NO_CLAIM) & ~body)
    return out


def later_view_check(then: LaterClaim, now: EgoGridEvidence, ego_pose: tuple[float, float, float],
                     road: torch.Tensor | None, reach_m: float, size_m: float) -> LaterVerdict:
    """A sender's claims of an earlier frame against the ego's own rays now (now.names[0] is the ego; road: the
    drivable area on this frame's grid, [G, G] bool, None: everywhere)."""
    cells = now.vehicle.shape[-1]
    then_in_now = relative_pose(Pose(ego_pose[0], ego_pose[1], 0.0, ego_pose[2]),
                                Pose(then.ego_x, then.ego_y, 0.0, then.ego_yaw))
    rel = torch.tensor([then_in_now], dtype=torch.float32)  # [1, 3]: the ego's grid then, in its frame now
    masks = torch.stack([then.claimed, then.empty]).float()[None]  # [1, 2, G, G]
    warped, _ = warp_to_ego(masks, rel, size_m, mode="nearest")
    claimed, empty = warped[0, 0] > 0.5, warped[0, 1] > 0.5  # outside then's grid: neither
    on_road = torch.ones_like(claimed) if road is None else road
    n = int(np.ceil(reach_m / (size_m / cells)))

    def within_reach(mask: torch.Tensor) -> torch.Tensor:  # cells with a `mask` cell within n cells (a square)
        # a square's max is the max over its rows of the max over its columns: two 1-D pools of 2n+1, not one of
        # (2n+1)^2 (the later view's largest cost per frame)
        m = F.max_pool2d(mask.float()[None, None], (2 * n + 1, 1), stride=1, padding=(n, 0))
        return F.max_pool2d(m, (1, 2 * n + 1), stride=1, padding=(0, n))[0, 0] > 0.5

    ego_clear = now.clear[0] & ~now.occupied[0] & ~_near(cells, size_m, (0.0, 0.0), FOOTPRINT_M)
    phantom = claimed & ~within_reach(on_road & ~ego_clear)
    seen = now.occupied[0] & (now.vehicle[0] > CLAIM)
    removed = seen & ~within_reach(on_road & ~empty)
    cell_m2 = (size_m / cells) ** 2
    return LaterVerdict(then.frame, round(float(phantom.sum()) * cell_m2, 2), round(float(removed.sum()) * cell_m2, 2))
