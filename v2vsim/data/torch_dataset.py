"""PyTorch view of a recorded dataset: one sample = one frame seen by one CAV as the ego.

A sample holds what `CooperativePerception.forward` takes (per-agent LiDAR clouds, relative poses,
valid flags; ego first, then the other CAVs within `range_m` of the ego, in id order as in a run) and the
targets on the ego's BEV grid. Frames are read lazily from their .npz files, or from an OPV2V-layout folder
(v2vsim.data.opv2v_read; `open_store` tells them apart).

`delays`: frames of V2V delay drawn per sample for the neighbours (0 = same frame). A neighbour
delayed by d contributes its frame k-d data warped with its frame k-d pose, while targets are of
frame k: the misalignment a late message causes in a run (DESIGN.md "Latency matters through pose").

`with_previous`: each agent's message before the one it contributes (the frame before its capture frame),
for receiver-side latency compensation (models.extrapolation): its frame index and its capture pose in the
frame of the agent's capture pose.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from v2vsim.data.layout import DatasetError, unpack_masks
from v2vsim.data.opv2v_read import OPV2VStore, is_opv2v
from v2vsim.data.store import FrameStore
from v2vsim.world.geometry import Pose, relative_pose


def open_store(root: Path | str) -> FrameStore:
    """The frames of a dataset folder: a native v2vsim dataset (manifest.json), or an OPV2V-layout folder
    (v2vsim.data.opv2v_read.OPV2VStore, read into the same frame keys)."""
    root = Path(root)
    if is_opv2v(root):
        return OPV2VStore(root)  # type: ignore[return-value]
    return FrameStore(root)


def _pose(poses: np.ndarray, cavs: list[str], c: str) -> Pose:
    return Pose(*(float(v) for v in poses[cavs.index(c)]))


def select_agents(cavs: list[str], poses: np.ndarray, ego: str, range_m: float, max_agents: int) -> list[str]:
    """The ego, then the other CAVs within range_m of it, at most max_agents in all."""
    e = _pose(poses, cavs, ego)
    others = []
    for c in cavs:
        if c == ego:
            continue
        p = _pose(poses, cavs, c)
        d = math.hypot(p.x - e.x, p.y - e.y)
        if d <= range_m:
            others.append((d, c))
    # The nearest ones when there are more than max_agents, in id order: the order the ego fuses in a run.
    return [ego] + sorted(c for _, c in sorted(others)[: max_agents - 1])


class CooperativeDataset(Dataset):
    """Samples of one split. Each item is a dict:

    "points": list of [P, 4] float32 clouds (ego first) — LiDAR inputs in each agent's body frame
    "images": list of [M, 3, h, w] uint8 camera images per agent (with_images), with "intrinsics" [M, 3, 3] and
    "extrinsics" [M, 4, 4] (camera to body); empty lists without
    "agents": list of agent ids; "rel_poses" [L, 3] (dx, dy, dyaw) in the ego frame; "valid" [L] bool
    "agent_frames": frame index each agent's data comes from (k - delay)
    with_previous: "prev_frames" the frame of each agent's previous message (agent_frames - 1; -1 when that
    frame does not exist or the agent was not a CAV in it); "prev_rel_poses" [L, 3] (dx, dy, dyaw) of its
    pose at prev_frames in its body frame at agent_frames (zeros where there is none)
    "vehicle" [S, S] bool: vehicles visible to some CAV (the scored target); "dynamic": all vehicles;
    "visible_self": vehicles the ego's own sensors saw; "road", "lane" [S, S] bool
    "boxes" [K, 5] visible GT boxes; "boxes_hidden" [J, 5] the others (ego frame); "boxes_self" /
    "boxes_self_hidden": the same split by what the ego's own sensors saw
    "key": SampleKey
    """

    def __init__(self, root: Path | str, split: str, max_agents: int = 5, range_m: float | None = None,
                 delays: Sequence[int] = (0,), egos: str = "all", stride: int = 1, seed: int = 0,
                 with_points: bool = True, with_images: bool = False, with_previous: bool = False) -> None:
        self.store = open_store(root)
        if hasattr(self.store, "check_targets"):  # OPV2V: refuse when BEV targets are missing (none made up)
            self.store.check_targets()
        self.split = split
        self.items = self.store.keys(split, egos=egos, stride=stride)
        if not self.items:
            raise DatasetError(f"{self.store.root}: split {split!r} has no frames")
        self.max_agents = max_agents
        self.range_m = range_m
        self.delays = tuple(delays)
        self.seed = seed
        self.epoch = 0
        self.with_points = with_points
        self.with_images = with_images
        self.with_previous = with_previous

    def __len__(self) -> int:
        return len(self.items)

    def _delay(self, i: int) -> int:
        if len(self.delays) == 1:
            return self.delays[0]
        rng = np.random.default_rng([self.seed, self.epoch, i])
        return int(self.delays[int(rng.integers(len(self.delays)))])

    def __getitem__(self, i: int) -> dict:
        key = self.items[i]
        run = self.store.runs[key.run]
        rng_m = self.range_m if self.range_m is not None else run["range_m"]
        cells = run["bev"]["cells"]
        delay = min(self._delay(i), key.frame)  # nothing was sent before frame 0
        with contextlib.ExitStack() as stack:
            f = stack.enter_context(self.store.frame(key.run, key.frame))
            cavs = [str(c) for c in f["cavs"]]
            poses = f["poses"]
            agents = select_agents(cavs, poses, key.ego, rng_m, self.max_agents)
            masks = unpack_masks(f[f"gt_{key.ego}"], cells)
            boxes, vis = f[f"boxes_{key.ego}"], f[f"boxvis_{key.ego}"]
            seen = set(str(x) for x in f[f"seen_{key.ego}"])
            own = np.array([str(x) in seen for x in f[f"boxids_{key.ego}"]], dtype=bool).reshape(-1)
            ego_pose = _pose(poses, cavs, key.ego)
            # Each agent's data and pose from the frame it was captured at: the ego's now, a neighbour's
            # `delay` frames earlier when it was present then.
            src = {c: key.frame for c in agents}
            files = {key.frame: (f, cavs, poses)}  # frame -> (file, its CAVs, their poses)
            if delay:
                g = stack.enter_context(self.store.frame(key.run, key.frame - delay))
                old = [str(c) for c in g["cavs"]]
                files[key.frame - delay] = (g, old, g["poses"])
                src.update({c: key.frame - delay for c in agents[1:] if c in old})
            agent_poses = {c: _pose(files[src[c]][2], files[src[c]][1], c) for c in agents}
            clouds = {c: files[src[c]][0][f"points_{c}"] for c in agents} if self.with_points else {}
            cams = {c: tuple(files[src[c]][0][f"{k}_{c}"] for k in ("images", "intrinsics", "extrinsics"))
                    for c in agents} if self.with_images else {}
            previous = self._previous(stack, key.run, agents, src, agent_poses) if self.with_previous else {}
        rel = np.array([relative_pose(ego_pose, agent_poses[c]) for c in agents], dtype=np.float32)
        return {
            **previous,
            "points": [torch.from_numpy(clouds[c].astype(np.float32)) for c in agents] if self.with_points else [],
            "images": [torch.from_numpy(cams[c][0]).permute(0, 3, 1, 2) for c in agents] if cams else [],
            "intrinsics": [torch.from_numpy(cams[c][1].astype(np.float32)) for c in agents] if cams else [],
            "extrinsics": [torch.from_numpy(cams[c][2].astype(np.float32)) for c in agents] if cams else [],
            "agents": agents,
            "agent_frames": [src[c] for c in agents],
            "rel_poses": torch.from_numpy(rel),
            "valid": torch.ones(len(agents), dtype=torch.bool),
            "vehicle": torch.from_numpy(masks["visible"]),
            "dynamic": torch.from_numpy(masks["dynamic"]),
            "visible_self": torch.from_numpy(masks["visible_self"]),
            "road": torch.from_numpy(masks["road"]),
            "lane": torch.from_numpy(masks["lane"]),
            "boxes": torch.from_numpy(boxes[vis].copy()),
            "boxes_hidden": torch.from_numpy(boxes[~vis].copy()),
            "boxes_self": torch.from_numpy(boxes[own].copy()),
            "boxes_self_hidden": torch.from_numpy(boxes[~own].copy()),
            "key": key,
        }

    def _previous(self, stack: contextlib.ExitStack, run: str, agents: list[str], src: dict[str, int],
                  poses: dict[str, Pose]) -> dict:
        """The previous message of each of `agents`: "prev_frames" and "prev_rel_poses" (class docstring)."""
        frames, rel = [], np.zeros((len(agents), 3), dtype=np.float32)
        opened: dict[int, tuple[list[str], np.ndarray]] = {}
        for j, c in enumerate(agents):
            k = src[c] - 1
            if k >= 0 and k not in opened:
                g = stack.enter_context(self.store.frame(run, k))
                opened[k] = ([str(x) for x in g["cavs"]], g["poses"])
            if k < 0 or c not in opened[k][0]:
                frames.append(-1)
                continue
            frames.append(k)
            rel[j] = relative_pose(poses[c], _pose(opened[k][1], opened[k][0], c))
        return {"prev_frames": frames, "prev_rel_poses": torch.from_numpy(rel)}


def collate(samples: list[dict]) -> dict:
    """Batch: "points" B lists of clouds, "rel_poses" [B, L, 3] and "valid" [B, L] padded to the largest
    L, masks stacked [B, S, S], box lists kept as lists; with images, "images" [B, L, M, 3, h, w] uint8,
    "intrinsics" [B, L, M, 3, 3], "extrinsics" [B, L, M, 4, 4] (padding: zero images, identity matrices);
    with_previous, "prev_rel_poses" [B, L, 3] padded like "rel_poses" and "prev_frames" B lists."""
    b, lmax = len(samples), max(len(s["agents"]) for s in samples)
    rel = torch.zeros(b, lmax, 3)
    valid = torch.zeros(b, lmax, dtype=torch.bool)
    for i, s in enumerate(samples):
        n = len(s["agents"])
        rel[i, :n] = s["rel_poses"]
        valid[i, :n] = True
    out: dict = {"points": [s["points"] for s in samples], "rel_poses": rel, "valid": valid}
    if "prev_rel_poses" in samples[0]:  # with_previous: [B, L, 3], zeros for padding
        prev = torch.zeros(b, lmax, 3)
        for i, s in enumerate(samples):
            prev[i, :len(s["agents"])] = s["prev_rel_poses"]
        out["prev_rel_poses"] = prev
        out["prev_frames"] = [s["prev_frames"] for s in samples]
    if samples[0]["images"]:
        m, _, h, w = samples[0]["images"][0].shape
        images = torch.zeros(b, lmax, m, 3, h, w, dtype=torch.uint8)
        intr = torch.eye(3).expand(b, lmax, m, 3, 3).clone()
        extr = torch.eye(4).expand(b, lmax, m, 4, 4).clone()
        for i, s in enumerate(samples):
            n = len(s["agents"])
            images[i, :n] = torch.stack(s["images"])
            intr[i, :n] = torch.stack(s["intrinsics"])
            extr[i, :n] = torch.stack(s["extrinsics"])
        out.update(images=images, intrinsics=intr, extrinsics=extr)
    for k in ("vehicle", "dynamic", "visible_self", "road", "lane"):
        out[k] = torch.stack([s[k] for s in samples])
    for k in ("boxes", "boxes_hidden", "boxes_self", "boxes_self_hidden", "key", "agents", "agent_frames"):
        out[k] = [s[k] for s in samples]
    return out


def tensor_inputs(batch: dict, device: torch.device | str = "cpu") -> tuple[object, Tensor, Tensor]:
    """(inputs, rel_poses, valid) of a batch on `device`, as CooperativePerception.forward takes them: the
    clouds, or (images in [0, 1], intrinsics, extrinsics) when the batch carries images."""
    if "images" in batch:
        inputs: object = (batch["images"].to(device).float().div(255.0), batch["intrinsics"].to(device),
                          batch["extrinsics"].to(device))
    else:
        inputs = [[p.to(device) for p in ps] for ps in batch["points"]]
    return inputs, batch["rel_poses"].to(device), batch["valid"].to(device)
