"""A fusion method from outside the package (issue 33): the example plugin (examples/fusion_plugin), installed into a
throwaway virtual environment as a researcher would install it (`pip install -e`), is listed by `v2vsim models`,
trains as a stage of its own on the frozen encoder's cached features, and runs beside a built-in with the weights it
was trained to. Nothing is installed outside the virtual environment."""

from __future__ import annotations

import importlib.metadata
import importlib.util
import io
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from models import zoo
from v2vsim.training.stages import TrainArgs
from v2vsim.training.train import run_stage

REPO = Path(__file__).resolve().parents[1]
PLUGIN = REPO / "examples" / "fusion_plugin"
NAME = "maxfuse"


def _why_no_install() -> str | None:
    """Why this interpreter cannot install the plugin offline into a venv without pip, or None when it can."""
    if importlib.util.find_spec("setuptools") is None:
        return "setuptools is not installed in this interpreter, and the build must not download it"
    pip = tuple(int(x) for x in importlib.metadata.version("pip").split(".")[:2] if x.isdigit())
    if pip < (22, 3):
        return "pip < 22.3 has no --python to install into a virtual environment created without pip"
    return None


@pytest.fixture(scope="module")
def venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A venv (system site-packages: torch & co) with the example plugin installed editable from a copy of it (the
    build writes nothing into the checkout); its python, which imports this checkout's v2vsim (PYTHONPATH)."""
    why = _why_no_install()
    if why:
        pytest.skip(why)
    root = tmp_path_factory.mktemp("plugin")
    src = root / "fusion_plugin"
    shutil.copytree(PLUGIN, src, ignore=shutil.ignore_patterns("*.egg-info", "build", "__pycache__"))
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", str(root / "venv")],
                   check=True, timeout=120)
    python = root / "venv" / "bin" / "python"
    done = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps",
                           "--no-build-isolation", "--no-index", "-e", str(src)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return python


def _v2vsim(python: Path, *args: str, cwd: Path, timeout: int = 300) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONHOME", "PYTHONSTARTUP")}
    env["PYTHONPATH"] = str(REPO)  # this checkout's v2vsim, whatever the system's site-packages hold
    return subprocess.run([str(python), "-m", "v2vsim.cli", *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)


def test_the_system_environment_does_not_see_the_plugin() -> None:
    """The install went into the venv only (and no other test left one behind)."""
    assert NAME not in [ep.name for ep in importlib.metadata.entry_points(group="v2vsim.fusion")]


def test_installed_plugin_is_listed_trains_and_runs(venv: Path, tiny_dataset: Path, tmp_path: Path) -> None:
    listed = _v2vsim(venv, "models", cwd=tmp_path)
    assert listed.returncode == 0, listed.stderr[-3000:]
    (row,) = [line for line in listed.stdout.splitlines() if line.split()[:1] == [NAME]]
    assert "fusion" in row and "plugin v2vsim-maxfuse 0.1.0" in row and "-> 1x64x64x64" in row
    assert "built-in" in next(line for line in listed.stdout.splitlines() if line.startswith("cobevt"))

    # The stages every fusion method builds on, here (no plugin needed): the single-agent model and the cache.
    out, work = tmp_path / "zoo", tmp_path / "work"
    small = {"epochs": 1, "samples_per_epoch": 2, "batch": 2, "val_samples": 2}
    for stage in ("single", "cache"):
        run_stage(TrainArgs(data=tiny_dataset, stage=stage, out=out, work=work, threads=1,
                            overrides=tuple(small.items())), log=io.StringIO())

    # The plugin's stage in the venv: 6 steps over the same 4 samples, the loss of each epoch's step recorded.
    trained = _v2vsim(venv, "train", "--data", str(tiny_dataset), "--stage", NAME, "--out", str(out), "--work",
                      str(work), "--threads", "1", "--epochs", "6", "--samples-per-epoch", "4", "--batch", "4",
                      "--val-samples", "2", "--val-every", "6", cwd=tmp_path)
    assert trained.returncode == 0, trained.stderr[-3000:]
    assert f"[{NAME}] epoch 6/6 validation: {NAME}: IoU veh" in trained.stderr
    history = torch.load(work / NAME / "last.pt", map_location="cpu", weights_only=False)["history"]
    losses = [h["loss"]["total"] for h in history]
    assert len(losses) == 6 and losses[-1] < 0.9 * losses[0], losses  # (measured: 6.57 -> 5.21, every epoch lower)
    entry = zoo.read_manifest(out)["zoos"]["pointpillars_tiny"]
    assert entry["methods"][NAME] == f"{NAME}.pt" and entry["files"][f"{NAME}.pt"]["stage"] == NAME
    state = torch.load(out / "pointpillars_tiny" / f"{NAME}.pt", weights_only=True)["state_dict"]
    assert {k.split(".")[0] for k in state} == {"fusion", "heads"}  # the encoder stays the single stage's
    assert state["fusion.mix.weight"].abs().sum() > 0  # learnt from its zero start

    run_dir = tmp_path / "run"
    ran = _v2vsim(venv, "run", str(REPO / "scenarios" / "intersection.yaml"), "--frames", "3", "--methods",
                  f"none,{NAME}", "--set", f"perception.weights={out}", "--set", "output.rerun=false", "--out",
                  str(run_dir), cwd=tmp_path, timeout=600)
    assert ran.returncode == 0, ran.stderr[-4000:]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["status"] == "complete" and metrics["frames"] == 3
    assert set(metrics["methods"]) == {"none", NAME}
    assert metrics["methods"][NAME]["iou_vehicle"] is not None
    assert metrics["checkpoints"] == {"none": None, NAME: f"pointpillars_tiny/{NAME}.pt"}
    # `none` has no checkpoint in this zoo: it ran untrained, and the run said so
    assert "none: no checkpoint in the zoo" in ran.stderr
    assert f"{NAME}: `pointpillars_tiny/{NAME}.pt`" in (run_dir / "report.md").read_text()
