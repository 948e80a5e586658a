"""The frames of a recorded v2vsim dataset (v2vsim.data.layout), read lazily (`FrameStore`), and the key of one
sample (`SampleKey`: a run's frame seen by one CAV as the ego). Numpy only: the OPV2V reader
(v2vsim.data.opv2v_read) gives its keys, the OPV2V writer reads frames through it, and the PyTorch view
(v2vsim.data.torch_dataset) takes either store."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from v2vsim.data.layout import DatasetError, frame_path, read_manifest, runs_of


@dataclass(frozen=True)
class SampleKey:
    run: str
    frame: int
    ego: str


class FrameStore:
    """Reads frames of one dataset lazily (npz members are inflated on access)."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.manifest = read_manifest(self.root)
        self.runs: dict[str, dict] = {}
        for r in self.manifest["runs"]:
            meta = self.root / r["name"] / "run.json"
            if not meta.is_file():
                raise DatasetError(f"{meta}: missing (the run listed in the manifest was not fully written)")
            self.runs[r["name"]] = {**r, **json.loads(meta.read_text())}

    def frame(self, run: str, k: int) -> np.lib.npyio.NpzFile:
        p = frame_path(self.root / run, k)
        if not p.is_file():
            raise DatasetError(f"{p}: frame file missing")
        return np.load(p)

    def keys(self, split: str, egos: str = "all", stride: int = 1) -> list[SampleKey]:
        """Every (run, frame, ego) of a split; egos "all" (each CAV present) or "first" (cav0 only)."""
        out = []
        for r in runs_of(self.manifest, split):
            for k in range(0, r["frames"], stride):
                with self.frame(r["name"], k) as f:
                    cavs = [str(c) for c in f["cavs"]]
                for c in (cavs if egos == "all" else cavs[:1]):
                    out.append(SampleKey(r["name"], k, c))
        return out
