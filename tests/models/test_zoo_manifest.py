"""models.zoo parses a manifest entry once into a frozen Zoo; an entry that is not as `register` writes it is refused
with one line naming the manifest and the key, before any checkpoint loads (and, through a scenario, before any
process starts: a ConfigError)."""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path

import pytest

from models import zoo
from v2vsim.config import ConfigError, load_scenario
from v2vsim.perception.checks import check_scenario

SHIPPED = zoo.read_manifest()


def _zoo_with(tmp_path: Path, edit) -> Path:
    """A zoo folder whose manifest is the shipped one after `edit(entry of pointpillars_tiny)` (no checkpoints:
    the parser refuses before any would load)."""
    doc = copy.deepcopy(SHIPPED)
    edit(doc["zoos"]["pointpillars_tiny"])
    (tmp_path / zoo.MANIFEST).write_text(json.dumps(doc))
    return tmp_path


def _refused(root: Path) -> str:
    with pytest.raises(zoo.ZooError) as e:
        zoo.find("pointpillars", "tiny", root)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{root / zoo.MANIFEST}: key /zoos/pointpillars_tiny/"), msg
    return msg


def test_the_shipped_zoos_parse_into_frozen_objects() -> None:
    z = zoo.find("pointpillars", "tiny")
    assert (z.root, z.encoder, z.preset, z.cells, z.wire_ratio) == (zoo.WEIGHTS_DIR, "pointpillars", "tiny", 64, 8)
    assert z.encoder_file == z.files["single.pt"] and z.methods["late"] == z.methods["none"] == z.files["none.pt"]
    assert z.method("cobevt", 16).path.name == "cobevt_r16.pt" and z.method("cobevt", 8) is z.methods["cobevt"]
    assert z.method("attfuse", 16) is None and z.wire_ratios("cobevt") == [1, 8, 16, 32, 64]
    assert z.compressors[8].sha256 == SHIPPED["zoos"]["pointpillars_tiny"]["files"]["compressor_r8.pt"]["sha256"]
    assert dict(z.extrapolation["cobevt"].trained_on) == {"cobevt.pt": z.methods["cobevt"].sha256}
    aligned = z.aligned["sinbevt"]
    assert (aligned.image_backbone, aligned.blocks) == ("efficientnet_lite0", 2)
    assert aligned.checkpoint.trained_on["single.pt"] == z.encoder_file.sha256
    with pytest.raises(dataclasses.FrozenInstanceError):
        z.cells = 32  # type: ignore[misc]
    with pytest.raises(TypeError):
        z.methods["cobevt"] = z.methods["none"]  # type: ignore[index]
    camera = zoo.find("sinbevt", "tiny")
    assert camera.image_backbone == "efficientnet_lite0" and camera.wire_ratio == 1 and not camera.compressors
    assert zoo.find("pointpillars", "paper") is None  # nothing ships for it: random weights


@pytest.mark.parametrize(("edit", "key", "what"), [
    (lambda e: e.pop("methods"), "methods", "missing"),
    (lambda e: e.pop("files"), "files", "missing"),
    (lambda e: e["files"]["cobevt.pt"].pop("sha256"), "files/cobevt.pt/sha256", "missing"),
    (lambda e: e["files"]["cobevt_extrapolate.pt"]["extrapolates"].pop("file"),
     "files/cobevt_extrapolate.pt/extrapolates/file", "missing"),
], ids=["methods", "files", "sha256", "extrapolates"])
def test_a_missing_key_is_named(tmp_path, edit, key: str, what: str) -> None:
    msg = _refused(_zoo_with(tmp_path, edit))
    assert f"key /zoos/pointpillars_tiny/{key}: {what}; restore it from git or rebuild with: make zoo" in msg


@pytest.mark.parametrize(("edit", "key", "expected"), [
    (lambda e: e.update(cells="64"), "cells", 'an integer expected, not "64"'),
    (lambda e: e.update(wire_ratio=True), "wire_ratio", "an integer expected, not true"),
    (lambda e: e.update(methods=["none.pt"]), "methods", "an object expected"),
    (lambda e: e["methods"].update(cobevt=3), "methods/cobevt", "a string expected, not 3"),
    (lambda e: e.update(encoder=1), "encoder", "a string or null expected, not 1"),
    (lambda e: e["files"]["none.pt"].update(sha256=None), "files/none.pt/sha256", "a string expected, not null"),
    (lambda e: e["compressors"].update(eight="compressor_r8.pt"), "compressors/eight", "a compression ratio"),
    (lambda e: e["wire_methods"].update({"16": "cobevt_r16.pt"}), "wire_methods/16", "an object expected"),
    (lambda e: e["files"]["align_sinbevt.pt"]["aligns"].update(blocks="2"), "files/align_sinbevt.pt/aligns/blocks",
     "an integer expected"),
], ids=["cells", "wire_ratio", "methods", "method file", "encoder", "sha256", "ratio", "wire_methods", "blocks"])
def test_a_key_of_the_wrong_type_is_named(tmp_path, edit, key: str, expected: str) -> None:
    assert f"key /zoos/pointpillars_tiny/{key}: {expected}" in _refused(_zoo_with(tmp_path, edit))


@pytest.mark.parametrize(("edit", "key", "what"), [
    (lambda e: e["extrapolation"].update(v2vnet=e["extrapolation"].pop("cobevt")) or e["methods"].pop("v2vnet"),
     "extrapolation/v2vnet", "unknown method (the zoo holds no v2vnet checkpoint)"),
    (lambda e: e["methods"].update({"CoBEVT": "cobevt.pt"}), "methods/CoBEVT", "not a method name"),
    (lambda e: e["wire_methods"]["16"].update(encoder="single.pt"), "wire_methods/16/encoder", "not a method name"),
], ids=["extrapolation of no method", "methods", "wire_methods"])
def test_an_unknown_method_is_named(tmp_path, edit, key: str, what: str) -> None:
    assert f"key /zoos/pointpillars_tiny/{key}: {what}" in _refused(_zoo_with(tmp_path, edit))


def test_a_manifest_without_zoos_is_refused(tmp_path) -> None:
    (tmp_path / zoo.MANIFEST).write_text(json.dumps({"format": "v2vsim-zoo", "version": 1}))
    with pytest.raises(zoo.ZooError, match=r"manifest\.json: key /zoos: missing; restore it from git"):
        zoo.find("pointpillars", "tiny", tmp_path)


def test_a_malformed_manifest_stops_a_scenario_before_any_process_starts(tmp_path) -> None:
    root = _zoo_with(tmp_path, lambda e: e["files"]["single.pt"].update(sha256=7))
    sc = load_scenario("scenarios/intersection.yaml", [f"perception.weights={root}"])
    with pytest.raises(ConfigError) as e:
        check_scenario(sc)
    assert str(e.value) == (f"{root / zoo.MANIFEST}: key /zoos/pointpillars_tiny/files/single.pt/sha256: a string "
                            f"expected, not 7; restore it from git or rebuild with: {zoo.REBUILD}")
