"""Features of the frozen single-agent encoder, computed once per (run, frame, CAV) and stored as
float16 — exactly the payload of a feature message on the wire — so that every intermediate method
trains on the very messages it fuses in a run, at a fraction of the cost of re-encoding."""

from __future__ import annotations

import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from v2vsim.data.layout import runs_of
from v2vsim.data.store import FrameStore

ENCODER_FILE = "encoder.json"  # which encoder wrote the cache: {"source": ..., "fingerprint": ...}


def encoder_fingerprint(state: dict) -> str:
    """sha256 over an encoder's state_dict (names and tensor bytes, in name order)."""
    h = hashlib.sha256()
    for k in sorted(state):
        h.update(k.encode())
        h.update(state[k].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def write_cache_encoder(folder: Path, source: str, state: dict) -> None:
    (folder / ENCODER_FILE).write_text(json.dumps({"source": source, "fingerprint": encoder_fingerprint(state)}))


def read_cache_encoder(folder: Path) -> dict | None:
    """{"source", "fingerprint"} of the encoder that wrote the cache; None for a cache written before this
    was recorded."""
    p = folder / ENCODER_FILE
    return json.loads(p.read_text()) if p.is_file() else None


class FeatureCache:
    """Read side: (run, frame, cav) -> [C, F, F] float16 (memory-mapped)."""

    def __init__(self, folder: Path) -> None:
        meta = json.loads((folder / "index.json").read_text())
        self.index: dict[str, int] = meta["index"]
        self.shape = tuple(meta["shape"])
        self.data = np.memmap(folder / "features.f16", dtype=np.float16, mode="r", shape=self.shape)

    def get(self, run: str, frame: int, cav: str) -> np.ndarray:
        return self.data[self.index[f"{run}/{frame}/{cav}"]]


@torch.no_grad()
def build_feature_cache(encoder: nn.Module, store: FrameStore, splits: tuple[str, ...], folder: Path,
                        stride: int = 1, log=sys.stderr, camera: bool = False) -> FeatureCache:
    """Encode every CAV of every `stride`-th frame of `splits` (its LiDAR sweep, or with `camera` its four
    images); resumable (rows already written are kept)."""
    folder.mkdir(parents=True, exist_ok=True)
    keys = []
    for split in splits:
        for r in runs_of(store.manifest, split):
            for k in range(0, r["frames"], stride):
                with store.frame(r["name"], k) as f:
                    keys += [(r["name"], k, str(c)) for c in f["cavs"]]
    c, s = encoder.out_channels, encoder.out_cells
    shape = (len(keys), c, s, s)
    idx_path, data_path, done_path = folder / "index.json", folder / "features.f16", folder / "done.txt"
    index = {f"{r}/{k}/{cav}": i for i, (r, k, cav) in enumerate(keys)}
    fresh = not idx_path.is_file() or json.loads(idx_path.read_text())["index"] != index
    if fresh:
        idx_path.write_text(json.dumps({"shape": list(shape), "index": index}))
        done_path.write_text("0")
        data = np.memmap(data_path, dtype=np.float16, mode="w+", shape=shape)
    else:
        data = np.memmap(data_path, dtype=np.float16, mode="r+", shape=shape)
    start = int(done_path.read_text() or 0)
    encoder.eval()
    dev = next(encoder.parameters()).device
    t0 = time.monotonic()
    batch = 8
    opened: tuple = (None, None)
    for i in range(start, len(keys), batch):
        chunk = keys[i:i + batch]
        inputs = []
        for r, k, cav in chunk:
            if (r, k) != opened[0]:
                opened = ((r, k), store.frame(r, k))
            f = opened[1]
            if camera:
                inputs.append((torch.from_numpy(f[f"images_{cav}"]).permute(0, 3, 1, 2).float().div(255.0),
                               torch.from_numpy(f[f"intrinsics_{cav}"].astype(np.float32)),
                               torch.from_numpy(f[f"extrinsics_{cav}"].astype(np.float32))))
            else:
                inputs.append(torch.from_numpy(f[f"points_{cav}"].astype(np.float32)).to(dev))
        if camera:  # [b, M, 3, h, w], [b, M, 3, 3], [b, M, 4, 4]
            feats = encoder(*(torch.stack([x[i] for x in inputs]).to(dev) for i in range(3)))
        else:
            feats = encoder(inputs)  # [b, C, F, F]
        data[i:i + len(chunk)] = feats.float().cpu().numpy().astype(np.float16)
        n = i + len(chunk)
        if (n // batch) % 25 == 0 or n == len(keys):
            data.flush()
            done_path.write_text(str(n))
        rate = (n - start) / max(time.monotonic() - t0, 1e-9)
        print(f"\rcache: {n}/{len(keys)} CAV frames  {rate:.1f}/s  ETA {(len(keys) - n) / max(rate, 1e-9):.0f} s ",
              end="", file=log, flush=True)
    data.flush()
    done_path.write_text(str(len(keys)))
    print(file=log)
    return FeatureCache(folder)
