"""A minimal PCD (Point Cloud Data, v0.7) writer and reader for LiDAR sweeps: x, y, z, intensity.

OPV2V's sweeps were written by Open3D, which keeps no intensity field: OpenCDA stored the intensity as the
red channel of the point colours (a packed `rgb` field), and OpenCOOD reads it back as `colors[:, 0]`.
`write_pcd` writes both an `rgb` field (red = round(255 x intensity), so Open3D/OpenCOOD read the intensity
as they read OPV2V's) and a float `intensity` field (full precision, ignored by Open3D's legacy reader).
`read_pcd` takes `intensity` when present, else the red channel of `rgb`/`rgba` / 255; a file with neither
is refused rather than read with made-up intensities. DATA ascii and binary are read; binary_compressed is not.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HEADER_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
_NUMPY = {("F", 4): "<f4", ("F", 8): "<f8", ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8",
          ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8"}


class PcdError(ValueError):
    """A PCD file this reader cannot read; the message names the file."""


def _pack_red(intensity: np.ndarray) -> np.ndarray:
    """(P,) intensity in [0, 1] -> (P,) float32 whose bits are the packed colour 0x00RR0000 (PCL's `rgb`)."""
    red = np.clip(np.rint(np.asarray(intensity, dtype=np.float64) * 255.0), 0, 255).astype(np.uint32)
    return (red << np.uint32(16)).view(np.float32)


def write_pcd(path: Path, points: np.ndarray, binary: bool = True) -> None:
    """Write (P, 4) x, y, z, intensity as a PCD v0.7 file with fields x y z rgb intensity (float32)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 4)
    n = len(pts)
    rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4"), ("intensity", "<f4")])
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["rgb"] = _pack_red(pts[:, 3])
    rec["intensity"] = pts[:, 3]
    header = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z rgb intensity\n"
              "SIZE 4 4 4 4 4\nTYPE F F F F F\nCOUNT 1 1 1 1 1\n"
              f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
              f"DATA {'binary' if binary else 'ascii'}\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        if binary:
            f.write(rec.tobytes())
        else:
            cols = [rec[k].astype(np.float64) for k in ("x", "y", "z")]
            body = np.column_stack(cols)
            for (x, y, z), rgb, inten in zip(body, rec["rgb"], rec["intensity"], strict=True):
                f.write(f"{x:.9g} {y:.9g} {z:.9g} {float(rgb):.9g} {float(inten):.9g}\n".encode("ascii"))


def read_pcd(path: Path) -> np.ndarray:
    """(P, 4) float32 x, y, z, intensity of a PCD file (ascii or binary); PcdError when it cannot."""
    path = Path(path)
    raw = path.read_bytes()
    head: dict[str, list[str]] = {}
    pos = 0
    while "DATA" not in head:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise PcdError(f"{path}: PCD header ends before its DATA line")
        line = raw[pos:end].decode("ascii", "replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        head[key.upper()] = vals
    for key in ("FIELDS", "SIZE", "TYPE", "DATA"):
        if key not in head:
            raise PcdError(f"{path}: PCD header has no {key} line")
    fields = head["FIELDS"]
    sizes = [int(s) for s in head["SIZE"]]
    types = [t.upper() for t in head["TYPE"]]
    counts = [int(c) for c in head.get("COUNT", ["1"] * len(fields))]
    if not len(fields) == len(sizes) == len(types) == len(counts):
        raise PcdError(f"{path}: FIELDS, SIZE, TYPE and COUNT differ in length")
    n = int(head["POINTS"][0]) if "POINTS" in head else int(head["WIDTH"][0]) * int(head.get("HEIGHT", ["1"])[0])
    layout = []
    for name, size, typ, count in zip(fields, sizes, types, counts, strict=True):
        if (typ, size) not in _NUMPY:
            raise PcdError(f"{path}: field {name!r} of TYPE {typ} SIZE {size} is not supported")
        layout.append((name, _NUMPY[(typ, size)], (count,)) if count > 1 else (name, _NUMPY[(typ, size)]))
    dtype = np.dtype(layout)
    mode = head["DATA"][0].lower()
    if mode == "binary":
        if len(raw) - pos < n * dtype.itemsize:
            raise PcdError(f"{path}: {n} points of {dtype.itemsize} bytes announced, {len(raw) - pos} bytes follow")
        rec = np.frombuffer(raw, dtype=dtype, count=n, offset=pos)
    elif mode == "ascii":
        rows = [ln.split() for ln in raw[pos:].decode("ascii", "replace").splitlines() if ln.strip()]
        width = sum(counts)
        if len(rows) < n or any(len(r) != width for r in rows[:n]):
            raise PcdError(f"{path}: expected {n} rows of {width} values")
        rec = np.empty(n, dtype=dtype)
        col = 0
        for name, typ, count in zip(fields, types, counts, strict=True):
            vals = np.array([r[col:col + count] for r in rows[:n]], dtype=np.float64 if typ == "F" else np.int64)
            if typ == "F" and dtype[name].base == np.dtype("<f4"):
                vals = vals.astype(np.float32)  # exact for what was printed from float32 (packed rgb included)
            rec[name] = vals.reshape(rec[name].shape)
            col += count
    else:
        raise PcdError(f"{path}: DATA {mode} is not supported (ascii or binary; re-save without compression)")
    names = set(fields)
    if not {"x", "y", "z"} <= names:
        raise PcdError(f"{path}: no x, y, z fields (FIELDS {' '.join(fields)})")
    out = np.empty((n, 4), dtype=np.float32)
    out[:, 0], out[:, 1], out[:, 2] = rec["x"], rec["y"], rec["z"]
    if "intensity" in names:
        out[:, 3] = rec["intensity"]
    elif "rgb" in names or "rgba" in names:
        packed = np.ascontiguousarray(rec["rgb" if "rgb" in names else "rgba"])
        bits = packed.view(np.uint32) if packed.dtype.itemsize == 4 else packed.astype(np.uint32)
        out[:, 3] = ((bits >> np.uint32(16)) & np.uint32(0xFF)).astype(np.float32) / 255.0
    else:
        raise PcdError(f"{path}: no intensity: FIELDS {' '.join(fields)} has neither `intensity` nor `rgb` "
                       "(OPV2V keeps the intensity in the red channel of `rgb`)")
    return out
