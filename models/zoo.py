"""The model zoo: shipped checkpoints in models/weights/<encoder>_<preset>/ and their manifest, which `find`
parses, one entry at a time, into a frozen `Zoo`: every reader works from that object, none from the JSON.

    models/weights/manifest.json
      {"format": "v2vsim-zoo", "version": 1,
       "zoos": {"pointpillars_tiny": {
           "encoder": "single.pt",             # the encoder every CAV runs (single-agent stage)
           "methods": {"none": "none.pt", "late": "none.pt", "cobevt": "cobevt.pt", ...},
           "files": {"cobevt.pt": {"sha256": ..., "bytes": ..., "stage": ..., "command": ...,
                                   "data": {...}, "wall_s": ..., "validation": {...}}, ...},
           "cells": 64, "compressors": {"8": "compressor_r8.pt", ...}, "wire_ratio": 8,   # the rest: optional
           "wire_methods": {"16": {"cobevt": "cobevt_r16.pt"}},
           "extrapolation": {"cobevt": "cobevt_extrapolate.pt"}, "aligned": {"sinbevt": "align_sinbevt.pt"}}}}

"cells" (LiDAR zoos): the fusion grid F the zoo was trained at (models.presets: a preset's `cells` is only
the default of a new zoo); models are built at the zoo's grid (Zoo.cells). An entry without it predates
the key and was trained at 32 x 32.

"image_backbone" (camera zoos): the image backbone the encoder was trained with (models.image_backbone); an
entry without it predates the key and holds the from-scratch "resnet" zoo. Models are built with the zoo's
backbone (Zoo.image_backbone), a new zoo with the preset's.

"compressors" (the `compress` training stage): the trained 1 x 1 channel compressor of each ratio r
(models.compression: sender C -> C/r, receiver C/r -> C), shared by every intermediate method (it is part of
the wire message, like the float16 payload); "wire_ratio": the ratio a scenario's comm.channel_compression:
null means for this zoo (the fusion stages train with it); "wire_methods": per other ratio, the fusion
methods trained on that wire (`v2vsim train --wire-ratio R`; their file records say "wire_ratio": R).

"extrapolation" (the `extrapolate` stage) and "aligned" (the `align` stage) name add-ons, not methods: per
method a receiver-side latency compensation (models.extrapolation), per camera encoder one backward-aligned
into this zoo's space (models.aligner). Each file record names the base checkpoints it was trained on top of
("extrapolates", "aligns": "base"), which must still be the zoo's for the add-on to load.

A checkpoint file is a dict {"format": "v2vsim-weights", "encoder", "preset", "stage", "methods",
"config", "state_dict"}; state_dict keys are prefixed "encoder.", "fusion.", "heads." (an extrapolation
add-on's: "extrapolation.").
Every file is checked against its sha256 before it is loaded.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import torch

from models.registration import METHOD_NAME, RESERVED

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
MANIFEST = "manifest.json"
REBUILD = "make zoo (LiDAR) or make zoo-camera (SinBEVT, LaRa)"
# The command that rebuilds one encoder's whole zoo from scratch (Makefile).
REBUILD_ZOO = {"pointpillars": "make zoo", "sinbevt": "make zoo-camera", "lara": "make zoo-camera"}


class ZooError(ValueError):
    """A missing or corrupted checkpoint, or a malformed manifest: one line naming the file and the command that
    rebuilds it (or the key). A ValueError, so that `v2vsim train` reports it as it reports bad input."""


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def zoo_name(encoder: str, preset: str) -> str:
    return f"{encoder}_{preset}"


def read_manifest(root: Path = WEIGHTS_DIR) -> dict:
    """The manifest as JSON data, for `register` to edit; readers parse an entry once, with `find`."""
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


LEGACY_CELLS = 32  # the grid of a LiDAR zoo entry written before "cells" was recorded
LEGACY_IMAGE_BACKBONE = "resnet"  # a camera zoo entry written before "image_backbone" was recorded


def zoo_image_backbone(raw: Mapping[str, Any] | None) -> str | None:
    """The image backbone of an entry as JSON (the one reading of the key and its legacy default, for the parser
    and `register`); None (the preset's) when the entry holds no files."""
    if raw is None or not raw.get("files"):
        return None
    return str(raw.get("image_backbone", LEGACY_IMAGE_BACKBONE))


@dataclass(frozen=True)
class Checkpoint:
    """One file of a zoo as its manifest lists it. `sha256` is None for a file a key names but "files" does not
    list (`load` refuses it, as it refuses a missing or altered file); `trained_on` ({file: sha256}) names the
    checkpoints an add-on was trained on top of, which whoever loads it checks are still the zoo's."""

    path: Path
    sha256: str | None
    stage: str | None = None
    wire_ratio: int | None = None  # a fusion method trained on this wire rather than the zoo's ("wire_methods")
    trained_on: Mapping[str, str] = field(default_factory=lambda: MappingProxyType({}))

    @property
    def rebuild_command(self) -> str:
        """How to rebuild this file: the whole zoo, or its stage alone."""
        stage = self.stage
        if stage and self.wire_ratio is not None:  # a fusion method trained on another wire than the zoo's
            stage = f"{stage} --wire-ratio {self.wire_ratio}"
        encoder = self.path.parent.name.rsplit("_", 1)[0]  # the zoo's folder is <encoder>_<preset>
        flag = "" if encoder == "pointpillars" else f" --encoder {encoder}"
        return REBUILD_ZOO.get(encoder, REBUILD) + (
            f" (this stage alone: v2vsim train --data DATA{flag} --stage {stage} --out {self.path.parent.parent}; "
            "docs/training.md)" if stage else " (docs/training.md)")

    def load(self) -> dict:
        """The verified state_dict; ZooError naming the file and the command that rebuilds it otherwise."""
        path, command = self.path, self.rebuild_command
        if not path.is_file():
            raise ZooError(f"{path}: checkpoint missing; rebuild it with: {command}")
        if self.sha256 is None:
            raise ZooError(f"{path}: not listed in {path.parent.parent / MANIFEST}; rebuild with: {REBUILD}")
        digest = sha256(path)
        if digest != self.sha256:
            raise ZooError(f"{path}: sha256 {digest[:12]}… does not match the manifest's {self.sha256[:12]}… "
                           f"(corrupted or replaced); rebuild it with: {command}")
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001 - any unpickling failure is a corrupted file
            raise ZooError(f"{path}: cannot be read ({e}); rebuild it with: {command}") from None
        if not isinstance(ckpt, dict) or ckpt.get("format") != "v2vsim-weights":
            raise ZooError(f"{path}: not a v2vsim checkpoint; rebuild it with: {command}")
        return ckpt["state_dict"]


@dataclass(frozen=True)
class Aligned:
    """A camera encoder backward-aligned into this (LiDAR) zoo's space by the `align` stage, built with
    `image_backbone` and an Aligner of `blocks`; `checkpoint.trained_on` names the base files it was aligned to."""

    checkpoint: Checkpoint
    image_backbone: str | None
    blocks: int


@dataclass(frozen=True)
class Zoo:
    """One encoder/preset entry of a manifest, parsed once (`find`), so that no reader needs its JSON layout.
    `cells` and `image_backbone` are what the zoo was trained at (their legacy defaults: module docstring);
    `wire_ratio` is the wire a scenario's comm.channel_compression: null means. Each method's checkpoint on that
    wire is in `methods`, on other wires in `wire_methods`: `method` picks the one a wire loads."""

    root: Path  # the folder of manifest.json
    encoder: str
    preset: str
    cells: int
    image_backbone: str | None
    wire_ratio: int
    encoder_file: Checkpoint | None  # the encoder every CAV runs (the `single` stage)
    methods: Mapping[str, Checkpoint]
    wire_methods: Mapping[int, Mapping[str, Checkpoint]]
    compressors: Mapping[int, Checkpoint]
    extrapolation: Mapping[str, Checkpoint]  # per method, its latency-compensation add-on
    aligned: Mapping[str, Aligned]  # per camera encoder
    files: Mapping[str, Checkpoint]  # every file the entry lists, by name

    @property
    def name(self) -> str:
        return zoo_name(self.encoder, self.preset)

    def method(self, method: str, ratio: int | None = None) -> Checkpoint | None:
        """The checkpoint of `method` ("encoder": the CAVs' encoder) trained on the ratio-`ratio` wire (None: the
        zoo's own); None if the zoo has none."""
        if method == "encoder":
            return self.encoder_file
        if ratio is None or ratio == self.wire_ratio:
            return self.methods.get(method)
        return self.wire_methods.get(ratio, {}).get(method)

    def wire_ratios(self, method: str) -> list[int]:
        """The wire ratios `method` has a checkpoint for: the zoo's wire ratio and those of "wire_methods"."""
        extra = {r for r, methods in self.wire_methods.items() if method in methods}
        return sorted(extra | {self.wire_ratio} if method in self.methods else extra)


def zoo_entry(encoder: str, preset: str, root: Path = WEIGHTS_DIR) -> dict | None:
    """The JSON record of one encoder/preset (None: none ships), as `register` writes it: for whoever inspects the
    manifest as data; readers parse it once, with `find`."""
    doc, at = read_manifest(root), root / MANIFEST
    if not isinstance(doc, dict):
        raise _malformed(at, "/", "a JSON object expected")
    return _get(_get(doc, "zoos", dict, at, "", required=True), zoo_name(encoder, preset), dict, at, "/zoos")


def find(encoder: str, preset: str, root: Path = WEIGHTS_DIR) -> Zoo | None:
    """The zoo of encoder/preset at `root`, parsed; None when none ships there. ZooError, one line naming the
    manifest and the key, for an entry that is not as `register` writes it: refused before anything loads."""
    raw = zoo_entry(encoder, preset, root)
    return None if raw is None else _parse(raw, root, encoder, preset)


def _malformed(at: Path, key: str, what: str) -> ZooError:
    return ZooError(f"{at}: key {key}: {what}; restore it from git or rebuild with: {REBUILD}")


_KINDS = {dict: "an object", str: "a string", int: "an integer", type(None): "null"}


def _get(raw: Mapping[str, Any], key: str, kind: type | tuple[type, ...], at: Path, where: str,
         default: Any = None, required: bool = False) -> Any:
    """raw[key] where it is a `kind` (`default` where it is absent and not `required`), else ZooError."""
    if key not in raw:
        if required:
            raise _malformed(at, f"{where}/{key}", "missing")
        return default
    value, kinds = raw[key], kind if isinstance(kind, tuple) else (kind,)
    if not isinstance(value, kinds) or (isinstance(value, bool) and int in kinds):
        raise _malformed(at, f"{where}/{key}", f"{' or '.join(_KINDS[k] for k in kinds)} expected, not "
                                              f"{json.dumps(value)[:40]}")
    return value


def _parse(raw: Mapping[str, Any], root: Path, encoder: str, preset: str) -> Zoo:
    """The Zoo of one manifest entry, every key it reads checked first (a file record's other keys, its training
    record, are data for whoever reads them)."""
    at, where, folder = root / MANIFEST, f"/zoos/{zoo_name(encoder, preset)}", root / zoo_name(encoder, preset)

    def get(obj: Mapping[str, Any], key: str, kind: Any, sub: str = "", default: Any = None,
            required: bool = False) -> Any:
        return _get(obj, key, kind, at, where + sub, default, required)

    def table(obj: Mapping[str, Any], key: str, sub: str = "", names: str = "", kind: type = str,
              required: bool = False) -> dict[str, Any]:
        """obj[key], {name: a `kind`}, each name a method's (names="method") or a ratio's (names="ratio")."""
        out = get(obj, key, dict, sub, {}, required)
        for k in out:
            if names == "ratio" and not (k.isdigit() and int(k) > 0):
                raise _malformed(at, f"{where}{sub}/{key}/{k}", "a compression ratio (a positive integer) expected")
            if names == "method" and (not METHOD_NAME.fullmatch(k) or k in RESERVED):
                raise _malformed(at, f"{where}{sub}/{key}/{k}", "not a method name")
            get(out, k, kind, f"{sub}/{key}")
        return out

    def checkpoint(name: str, info: Mapping[str, Any]) -> Checkpoint:
        sub = f"/files/{name}"
        base = get(info, "extrapolates", dict, sub)
        on = {} if base is None else {get(base, "file", str, f"{sub}/extrapolates", required=True):
                                      get(base, "sha256", str, f"{sub}/extrapolates", required=True)}
        on.update(table(get(info, "aligns", dict, sub, {}), "base", f"{sub}/aligns"))
        return Checkpoint(folder / name, get(info, "sha256", str, sub, required=True),
                          get(info, "stage", (str, type(None)), sub), get(info, "wire_ratio", int, sub),
                          MappingProxyType(on))

    files_raw = table(raw, "files", kind=dict, required=True)
    files = {n: checkpoint(n, info) for n, info in files_raw.items()}

    def file(name: str) -> Checkpoint:  # a file "files" does not list: load() refuses it
        return files.get(name) or Checkpoint(folder / name, None)

    def checkpoints(obj: Mapping[str, Any], key: str, sub: str = "", required: bool = False) -> dict[str, Checkpoint]:
        return {m: file(n) for m, n in table(obj, key, sub, "method", required=required).items()}

    methods = checkpoints(raw, "methods", required=True)
    wires = table(raw, "wire_methods", names="ratio", kind=dict)
    wire_methods = {int(r): MappingProxyType(checkpoints(wires, r, "/wire_methods")) for r in wires}
    extrapolation = checkpoints(raw, "extrapolation")
    for m in extrapolation:
        if m not in methods and not any(m in ms for ms in wire_methods.values()):
            raise _malformed(at, f"{where}/extrapolation/{m}", f"unknown method (the zoo holds no {m} checkpoint)")
    aligned = {}
    for enc, n in table(raw, "aligned").items():
        sub = f"/files/{n}/aligns"
        aligns = get(files_raw.get(n, {}), "aligns", dict, f"/files/{n}", {})
        aligned[enc] = Aligned(file(n), get(aligns, "image_backbone", (str, type(None)), sub),
                               get(aligns, "blocks", int, sub, 2))
    encoder_file = get(raw, "encoder", (str, type(None)))
    get(raw, "image_backbone", str)  # checked; read (with its legacy default) by zoo_image_backbone
    return Zoo(root=root, encoder=encoder, preset=preset, cells=get(raw, "cells", int, default=LEGACY_CELLS),
               image_backbone=zoo_image_backbone(raw), wire_ratio=get(raw, "wire_ratio", int, default=1),
               encoder_file=None if encoder_file is None else file(encoder_file),
               methods=MappingProxyType(methods), wire_methods=MappingProxyType(wire_methods),
               compressors=MappingProxyType({int(r): file(n) for r, n in table(raw, "compressors", names="ratio")
                                             .items()}),
               extrapolation=MappingProxyType(extrapolation), aligned=MappingProxyType(aligned),
               files=MappingProxyType(files))


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
