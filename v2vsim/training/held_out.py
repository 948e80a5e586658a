"""Train and test worlds that never meet: no network or building file the benchmark reads may be in a training or
validation set (issue 65).

Files are compared by content (sha256), not by name, so a copied or renamed benchmark network is caught too. Each
recorded run keeps the hashes of the files its world was built from (run.json "inputs", v2vsim/data/record.py);
a run recorded before that field existed is hashed from its scenario file, when that still loads. `v2vsim train`
refuses a dataset whose train or val split holds a match, naming the run and the benchmark family, and every zoo
checkpoint lists the hashes it was trained on (manifest "data" -> "inputs_sha256"), which a test holds against the
catalogue.
"""

from __future__ import annotations

import json
from pathlib import Path

from models.zoo import sha256 as sha256_file
from v2vsim.data.layout import DatasetError, read_manifest, runs_of


def benchmark_inputs(catalogue: Path | None = None) -> dict[str, str]:
    """{sha256: "family: file"} of every network and building file the catalogue's families read."""
    from v2vsim.config import load_scenario
    from v2vsim.study.catalogue import load_catalogue

    out: dict[str, str] = {}
    for fam in load_catalogue(catalogue).families:
        sc = load_scenario(str(fam.scenario))
        for path in (sc.traffic.net, sc.traffic.buildings):
            if path is not None:
                out.setdefault(sha256_file(Path(path)), f"{fam.name}: {Path(path).name}")
    return out


def _run_inputs(root: Path, run: dict) -> dict[str, str]:
    meta_path = root / run["name"] / "run.json"
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    if "inputs" in meta:
        return meta["inputs"]
    source = meta.get("source")
    if source and Path(source).is_file():  # recorded before run.json kept its inputs
        from v2vsim.config import load_scenario
        from v2vsim.data.record import scenario_inputs

        return scenario_inputs(load_scenario(source, tuple(meta.get("overrides", ()))))
    raise DatasetError(f"{meta_path}: no \"inputs\" (the hashes of its network and buildings) and its scenario "
                       f"{source!r} is not here to hash: record the run again with this v2vsim")


def dataset_inputs(root: Path, splits: tuple[str, ...] = ("train", "val")) -> dict[str, dict[str, str]]:
    """{run name: {"net": sha256, "buildings": sha256}} of the dataset's runs in `splits`."""
    doc = read_manifest(root)
    return {r["name"]: _run_inputs(root, r) for s in splits for r in runs_of(doc, s)}


def check_held_out(root: Path, catalogue: Path | None = None) -> dict[str, dict[str, str]]:
    """Raise DatasetError when a train or val run of dataset `root` was built from a benchmark file; else return
    the runs' inputs (dataset_inputs)."""
    bench = benchmark_inputs(catalogue)
    inputs = dataset_inputs(root)
    for name, files in sorted(inputs.items()):
        for kind, digest in files.items():
            if digest in bench:
                raise DatasetError(f"{root}: run {name} is built from a benchmark file ({kind} = {bench[digest]}); "
                                   "the benchmark's networks and buildings are held out of training and validation")
    return inputs


def is_v2vsim_dataset(root: Path) -> bool:
    """A dataset in v2vsim's own layout (an OPV2V folder has no such manifest and no recorded inputs)."""
    try:
        read_manifest(root)
    except DatasetError:
        return False
    return True


def data_inputs_sha256(root: Path) -> list[str]:
    """The distinct sha256 of every network and building file the dataset's train and val runs were built from
    (a zoo manifest entry keeps them; empty for a dataset of another layout)."""
    if not is_v2vsim_dataset(root):
        return []
    return sorted({d for files in dataset_inputs(root).values() for d in files.values()})
