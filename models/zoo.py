"""The model zoo: shipped checkpoints in models/weights/<encoder>_<preset>/ and their manifest.

    models/weights/manifest.json
      {"format": "v2vsim-zoo", "version": 1,
       "zoos": {"pointpillars_tiny": {
           "encoder": "single.pt",             # the encoder every CAV runs (single-agent stage)
           "methods": {"none": "none.pt", "late": "none.pt", "cobevt": "cobevt.pt", ...},
           "files": {"cobevt.pt": {"sha256": ..., "bytes": ..., "stage": ..., "command": ...,
                                   "data": {...}, "wall_s": ..., "validation": {...}}, ...},
           "extrapolation": {"cobevt": "cobevt_extrapolate.pt"}}}}   # optional

"cells" (LiDAR zoos): the fusion grid F the zoo was trained at (models.presets: a preset's `cells` is only
the default of a new zoo); models are built at the zoo's grid (zoo_cells). An entry without it predates
the key and was trained at 32 x 32.

"image_backbone" (camera zoos): the image backbone the encoder was trained with (models.image_backbone); an
entry without it predates the key and holds the from-scratch "resnet" zoo. Models are built with the zoo's
backbone (zoo_image_backbone), a new zoo with the preset's.

"compressors" (optional; the `compress` training stage): {"8": "compressor_r8.pt", ...}, the trained
1 x 1 channel compressor of each ratio r (models.compression: sender C -> C/r, receiver C/r -> C), shared
by every intermediate method (it is part of the wire message, like the float16 payload); "wire_ratio":
the ratio a scenario's comm.channel_compression: null means for this zoo (the fusion stages train with it).

"extrapolation" (optional; the `extrapolate` training stage): per method, a receiver-side latency
compensation module (models.extrapolation) trained on top of that method's checkpoint. It is an add-on,
not a method: "methods" still names each method's own file, and the add-on's file is listed in "files"
(stage "extrapolate") and verified like every other.

A checkpoint file is a dict {"format": "v2vsim-weights", "encoder", "preset", "stage", "methods",
"config", "state_dict"}; state_dict keys are prefixed "encoder.", "fusion.", "heads." (an extrapolation
add-on's: "extrapolation.").
Every file is checked against its sha256 before it is loaded.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import torch

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
MANIFEST = "manifest.json"
REBUILD = "make zoo (LiDAR) or make zoo-camera (SinBEVT, LaRa)"
# The command that rebuilds one encoder's whole zoo from scratch (Makefile).
REBUILD_ZOO = {"pointpillars": "make zoo", "sinbevt": "make zoo-camera", "lara": "make zoo-camera"}


class ZooError(Exception):
    """A missing or corrupted checkpoint: names the file and the command that rebuilds it."""


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def zoo_name(encoder: str, preset: str) -> str:
    return f"{encoder}_{preset}"


def read_manifest(root: Path = WEIGHTS_DIR) -> dict:
    path = root / MANIFEST
    if not path.is_file():
        return {"format": "v2vsim-zoo", "version": 1, "zoos": {}}
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ZooError(f"{path}: not valid JSON ({e}); restore it from git or rebuild with: {REBUILD}") from None


def write_manifest(doc: dict, root: Path = WEIGHTS_DIR) -> None:
    root.mkdir(parents=True, exist_ok=True)
    tmp = root / (MANIFEST + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1, sort_keys=False) + "\n")
    tmp.replace(root / MANIFEST)


def zoo_entry(encoder: str, preset: str, root: Path = WEIGHTS_DIR) -> dict | None:
    """The manifest entry of one encoder/preset, or None when no checkpoints ship for it."""
    return read_manifest(root)["zoos"].get(zoo_name(encoder, preset))


def method_file(entry: dict, method: str, root: Path, encoder: str, preset: str) -> Path | None:
    """The checkpoint of `method` ("encoder": the file with the CAVs' encoder), None if not shipped."""
    name = entry.get("encoder") if method == "encoder" else entry["methods"].get(method)
    return None if name is None else root / zoo_name(encoder, preset) / name


LEGACY_CELLS = 32  # the grid of a LiDAR zoo entry written before "cells" was recorded


def zoo_cells(entry: dict | None, default: int) -> int:
    """The fusion grid a zoo entry was trained at; `default` (the preset's) when there is no entry."""
    if entry is None:
        return default
    return int(entry.get("cells", LEGACY_CELLS))


LEGACY_IMAGE_BACKBONE = "resnet"  # a camera zoo entry written before "image_backbone" was recorded


def zoo_image_backbone(entry: dict | None) -> str | None:
    """The image backbone a camera zoo entry was trained with; None (the preset's) when it holds no files."""
    if entry is None or not entry.get("files"):
        return None
    return str(entry.get("image_backbone", LEGACY_IMAGE_BACKBONE))


def compressor_file(entry: dict, ratio: int, root: Path, encoder: str, preset: str) -> Path | None:
    """The trained channel compressor of `ratio`, None if the zoo has none."""
    name = (entry.get("compressors") or {}).get(str(ratio))
    return None if name is None else root / zoo_name(encoder, preset) / name


def wire_method_file(entry: dict, method: str, ratio: int, root: Path, encoder: str, preset: str) -> Path | None:
    """The checkpoint of intermediate `method` trained on the ratio-`ratio` wire (manifest "wire_methods"; the
    zoo's own wire ratio is its "methods" entry), None if the zoo has none."""
    if ratio == wire_ratio(entry):
        return method_file(entry, method, root, encoder, preset)
    name = ((entry.get("wire_methods") or {}).get(str(ratio)) or {}).get(method)
    return None if name is None else root / zoo_name(encoder, preset) / name


def wire_ratios_of(entry: dict, method: str) -> list[int]:
    """The wire ratios `method` has a checkpoint for: the zoo's wire ratio and those of "wire_methods"."""
    extra = [int(r) for r, methods in (entry.get("wire_methods") or {}).items() if method in methods]
    return sorted({wire_ratio(entry), *extra}) if method in entry["methods"] else sorted(extra)


def wire_ratio(entry: dict | None) -> int:
    """The channel compression ratio of this zoo's default wire message (1: uncompressed)."""
    return 1 if entry is None else int(entry.get("wire_ratio", 1))


def extrapolation_file(entry: dict, method: str, root: Path, encoder: str, preset: str) -> Path | None:
    """The latency-compensation add-on of `method` (models.extrapolation), None if the zoo has none."""
    name = (entry.get("extrapolation") or {}).get(method)
    return None if name is None else root / zoo_name(encoder, preset) / name


def rebuild_command(path: Path, entry: dict) -> str:
    """How to rebuild the checkpoint `path` of a zoo entry: the whole zoo, or its stage alone."""
    info = entry["files"].get(path.name) or {}
    stage = info.get("stage")
    if stage and info.get("wire_ratio") is not None:  # a fusion method trained on another wire than the zoo's
        stage = f"{stage} --wire-ratio {info['wire_ratio']}"
    encoder = path.parent.name.rsplit("_", 1)[0]  # the zoo's folder is <encoder>_<preset>
    whole = REBUILD_ZOO.get(encoder, REBUILD)
    flag = "" if encoder == "pointpillars" else f" --encoder {encoder}"
    return whole + (f" (this stage alone: v2vsim train --data DATA{flag} --stage {stage} --out {path.parent.parent}; "
                    f"docs/training.md)" if stage else " (docs/training.md)")


def load_checkpoint(path: Path, entry: dict) -> dict:
    """A verified checkpoint's state_dict; ZooError naming the file and the rebuild command otherwise."""
    info = entry["files"].get(path.name)
    command = rebuild_command(path, entry)
    if not path.is_file():
        raise ZooError(f"{path}: checkpoint missing; rebuild it with: {command}")
    if info is None:
        raise ZooError(f"{path}: not listed in {path.parent.parent / MANIFEST}; rebuild with: {REBUILD}")
    digest = sha256(path)
    if digest != info["sha256"]:
        raise ZooError(f"{path}: sha256 {digest[:12]}… does not match the manifest's {info['sha256'][:12]}… "
                       f"(corrupted or replaced); rebuild it with: {command}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unpickling failure is a corrupted file
        raise ZooError(f"{path}: cannot be read ({e}); rebuild it with: {command}") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != "v2vsim-weights":
        raise ZooError(f"{path}: not a v2vsim checkpoint; rebuild it with: {command}")
    return ckpt["state_dict"]


def save_checkpoint(path: Path, state_dict: dict, *, encoder: str, preset: str, stage: str, methods: list[str],
                    config: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    torch.save({"format": "v2vsim-weights", "encoder": encoder, "preset": preset, "stage": stage,
                "methods": methods, "config": config,
                "state_dict": {k: v.detach().cpu().clone() for k, v in state_dict.items()}}, tmp)
    tmp.replace(path)


def set_wire_ratio(encoder: str, preset: str, ratio: int, root: Path = WEIGHTS_DIR) -> None:
    """Make `ratio` (its compressor must be registered) the zoo's default wire ratio."""
    doc = read_manifest(root)
    entry = doc["zoos"][zoo_name(encoder, preset)]
    if str(ratio) not in (entry.get("compressors") or {}):
        raise ZooError(f"{root / MANIFEST}: no ratio-{ratio} compressor registered; train it first")
    entry["wire_ratio"] = ratio
    write_manifest(doc, root)


def register(path: Path, *, encoder: str, preset: str, methods: list[str], info: dict,
             root: Path = WEIGHTS_DIR, provides_encoder: bool = False, extrapolates: tuple[str, ...] = (),
             cells: int | None = None, compresses: int | None = None, trained_wire: int | None = None,
             image_backbone: str | None = None, aligns: str | None = None) -> None:
    """Add (or replace) a checkpoint file in the manifest, with its sha256 and size; `provides_encoder`:
    this file holds the encoder every CAV runs (the single-agent stage); `extrapolates`: methods whose
    latency-compensation add-on this file is (it then serves no method itself: pass methods=[]);
    `cells`: the LiDAR grid it was trained at (ZooError if the entry holds another grid's files);
    `compresses`: the ratio whose channel compressor this file is; `trained_wire`: the file holds `methods`
    trained on the wire of this ratio rather than the zoo's (listed under "wire_methods", not "methods");
    `image_backbone`: the camera image backbone it was trained with (ZooError if the entry holds another's);
    `aligns`: the camera encoder this file backward-aligns into this (LiDAR) zoo's space (listed under "aligned")."""
    doc = read_manifest(root)
    entry = doc["zoos"].setdefault(zoo_name(encoder, preset), {"encoder": None, "methods": {}, "files": {}})
    if cells is not None:
        have = entry.get("cells", LEGACY_CELLS if entry["files"] else cells)
        if have != cells:
            raise ZooError(f"{root / MANIFEST}: {zoo_name(encoder, preset)} holds a {have} x {have} zoo; a {cells} x "
                           f"{cells} checkpoint cannot join it (train into another --out)")
        entry["cells"] = cells
    if image_backbone is not None:
        have_bb = zoo_image_backbone(entry) or image_backbone
        if have_bb != image_backbone:
            raise ZooError(f"{root / MANIFEST}: {zoo_name(encoder, preset)} holds a zoo with the {have_bb} image "
                           f"backbone; a {image_backbone} checkpoint cannot join it (train into another --out)")
        entry["image_backbone"] = image_backbone
    if compresses is not None:
        entry.setdefault("compressors", {})[str(compresses)] = path.name
    if provides_encoder:
        entry["encoder"] = path.name
    entry["files"][path.name] = {"sha256": sha256(path), "bytes": path.stat().st_size, **info}
    for m in methods:
        if trained_wire is None:
            entry["methods"][m] = path.name
        else:
            entry.setdefault("wire_methods", {}).setdefault(str(trained_wire), {})[m] = path.name
    for m in extrapolates:
        entry.setdefault("extrapolation", {})[m] = path.name
    if aligns is not None:
        entry.setdefault("aligned", {})[aligns] = path.name
    write_manifest(doc, root)
