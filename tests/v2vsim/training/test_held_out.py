"""The benchmark's networks and buildings never enter training or validation (compared by content hash)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from models import zoo
from v2vsim.data.layout import FORMAT, VERSION, DatasetError
from v2vsim.training.held_out import benchmark_inputs, check_held_out, sha256_file

NETS = Path("scenarios/nets")


def _dataset(root: Path, runs: dict[str, tuple[str, Path, Path]]) -> Path:
    """A dataset manifest and run.json files only: {run: (split, net, buildings)} (no frames: the check reads
    none)."""
    root.mkdir(parents=True)
    doc = {"format": FORMAT, "version": VERSION, "runs": []}
    for name, (split, net, poly) in runs.items():
        (root / name).mkdir()
        (root / name / "run.json").write_text(json.dumps(
            {"scenario": name, "inputs": {"net": sha256_file(net), "buildings": sha256_file(poly)}}))
        doc["runs"].append({"name": name, "scenario": name, "seed": 0, "split": split, "frames": 1})
    (root / "manifest.json").write_text(json.dumps(doc))
    return root


def test_every_file_the_catalogue_reads_is_listed() -> None:
    bench = benchmark_inputs()
    for name in ("t_junction.net.xml", "t_junction_occluded.poly.xml", "crossroads.net.xml",
                 "crossroads_signal.net.xml", "crossroads_turn.net.xml", "crossroads_occluded.poly.xml",
                 "merge.net.xml", "merge.poly.xml"):
        assert sha256_file(NETS / name) in bench, name
    assert sha256_file(NETS / "intersection.net.xml") not in bench


def test_a_dataset_of_held_out_worlds_passes(tmp_path: Path) -> None:
    root = _dataset(tmp_path / "d", {"intersection_s1": ("train", NETS / "intersection.net.xml",
                                                          NETS / "intersection.poly.xml")})
    assert set(check_held_out(root)) == {"intersection_s1"}


@pytest.mark.parametrize("split", ["train", "val"])
def test_a_benchmark_network_is_refused_even_renamed(tmp_path: Path, split: str) -> None:
    copy = tmp_path / "my_town.net.xml"
    shutil.copy(NETS / "crossroads_turn.net.xml", copy)  # renamed: the content is what counts
    root = _dataset(tmp_path / "d", {"intersection_s1": ("train", NETS / "intersection.net.xml",
                                                          NETS / "intersection.poly.xml"),
                                     "my_town_s0": (split, copy, NETS / "intersection.poly.xml")})
    with pytest.raises(DatasetError, match="my_town_s0.*crossroads_turn.net.xml"):
        check_held_out(root)


def test_an_eval_split_may_hold_them(tmp_path: Path) -> None:
    root = _dataset(tmp_path / "d", {"lt_s0": ("eval", NETS / "crossroads_turn.net.xml",
                                              NETS / "crossroads_occluded.poly.xml")})
    assert check_held_out(root) == {}


def test_the_shipped_zoos_never_trained_on_a_benchmark_file() -> None:
    """Every zoo checkpoint that lists its training inputs by hash (those trained since issue 65) is disjoint from
    the catalogue's files."""
    bench = benchmark_inputs()
    for root in (Path("models/weights"), *sorted(Path("models/candidates").glob("*/"))):
        if not (root / "manifest.json").is_file():
            continue
        for entry in zoo.read_manifest(root)["zoos"].values():
            for name, info in entry.get("files", {}).items():
                hit = set(info.get("data", {}).get("inputs_sha256", [])) & set(bench)
                assert not hit, f"{root}/{name}: trained on {[bench[h] for h in hit]}"
