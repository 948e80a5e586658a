"""A built wheel is the whole product (issue 33): it holds every file of the model zoo and every shipped scenario
with its SUMO network, and, installed into a fresh virtual environment outside the checkout that sees none of this
machine's packages (its dependencies resolved by pip as declared, issue 44), `v2vsim run intersection` runs from
another folder on the zoo inside the installed package."""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
TOP_PACKAGES = ("v2vsim", "agents", "models")
DATA_PACKAGE = "v2vsim.scenarios"  # pyproject maps it onto the top-level scenarios/ folder
# What a build must not see: build outputs, runs and caches (setuptools keeps build/lib between builds, so a file
# deleted from the checkout would live on in a wheel built in place).
_TOP_LEVEL_JUNK = {".git", "build", "dist", "runs", "out", "data", ".venv", ".pytest_cache", ".ruff_cache"}
_ANY_LEVEL_JUNK = ("__pycache__", ".egg-info", ".rrd")


def _files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file() and "__pycache__" not in p.parts)


def _checkout_packages() -> set[str]:
    return {".".join(init.parent.relative_to(REPO).parts)
            for top in TOP_PACKAGES for init in (REPO / top).rglob("__init__.py")}


def _why_no_wheel_build() -> str | None:
    """Why this interpreter cannot build the wheel offline (no build isolation), or None when it can."""
    if importlib.util.find_spec("setuptools") is None:
        return "setuptools is not installed in this interpreter, and the build must not download it"
    version = tuple(int(x) for x in importlib.metadata.version("setuptools").split(".")[:2] if x.isdigit())
    if version < (70, 1) and importlib.util.find_spec("wheel") is None:  # bdist_wheel moved into setuptools 70.1
        return "setuptools < 70.1 without the wheel package cannot build a wheel offline"
    pip = tuple(int(x) for x in importlib.metadata.version("pip").split(".")[:2] if x.isdigit())
    if pip < (22, 3):
        return "pip < 22.3 has no --python to install into a virtual environment created without pip"
    return None


def test_pyproject_lists_every_package_of_the_checkout() -> None:
    """The packages are listed by hand in pyproject.toml (a data package maps onto scenarios/): a package added to
    the checkout and not there would be missing from every wheel."""
    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    assert listed - {DATA_PACKAGE} == _checkout_packages()


def _copy_source(dst: Path) -> None:
    def ignore(folder: str, names: list[str]) -> set[str]:
        top = Path(folder).resolve() == REPO
        return {n for n in names if (top and n in _TOP_LEVEL_JUNK) or n.endswith(_ANY_LEVEL_JUNK)}

    shutil.copytree(REPO, dst, ignore=ignore)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    why = _why_no_wheel_build()
    if why:
        pytest.skip(why)
    root = tmp_path_factory.mktemp("wheel")
    _copy_source(root / "src")
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                           "-w", str(root / "dist"), str(root / "src")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    (whl,) = (root / "dist").glob("v2vsim-*.whl")
    return whl


def test_wheel_holds_the_zoo_the_scenarios_and_every_module(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as z:
        sizes = {i.filename: i.file_size for i in z.infolist()}
    expected = {}
    for f in _files(REPO / "models" / "weights"):  # every zoo folder and the manifest
        expected[f.relative_to(REPO).as_posix()] = f.stat().st_size
    for f in [*sorted((REPO / "scenarios").glob("*.yaml")), *_files(REPO / "scenarios" / "nets")]:
        expected["v2vsim/scenarios/" + f.relative_to(REPO / "scenarios").as_posix()] = f.stat().st_size
    for top in TOP_PACKAGES:
        for f in (REPO / top).rglob("*.py"):
            if "candidates" not in f.parts:
                expected[f.relative_to(REPO).as_posix()] = f.stat().st_size
    assert len([n for n in expected if n.startswith("models/weights/")]) > 10  # the zoo is there to compare with
    missing = sorted(n for n in expected if n not in sizes)
    assert not missing, f"{len(missing)} files missing from {wheel.name}: {missing[:10]}"
    differ = sorted(n for n, size in expected.items() if sizes[n] != size)
    assert not differ, f"files whose size differs from the checkout's: {differ[:10]}"
    # candidates are work in progress, not the zoo
    assert not [n for n in sizes if n.startswith("models/candidates/")]


def _isolated_venv(venv: Path) -> Path:
    """A virtual environment that sees none of this interpreter's packages (no --system-site-packages): whatever
    the wheel needs must come from its declared dependencies. Fails if the venv can see site-packages outside."""
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    python = venv / "bin" / "python"
    probe = subprocess.run([str(python), "-c", "import json, sys; print(json.dumps(sys.path))"],
                           capture_output=True, text=True, timeout=60, env=_clean_env())
    leak = [p for p in json.loads(probe.stdout) if "site-packages" in p and not p.startswith(str(venv))]
    assert not leak, f"the venv sees site-packages outside itself: {leak}"
    return python


def _clean_env() -> dict[str, str]:
    """The environment without what would let this interpreter's packages back in."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP")}
    env["PYTHONNOUSERSITE"] = "1"
    return env


def _pip_install(python: Path, *args: str) -> None:
    """pip of the venv, resolving from the registry as a user's pip does (the README pins torch first)."""
    done = subprocess.run([str(python), "-m", "pip", "install", "--disable-pip-version-check", "--no-compile",
                           *args], capture_output=True, text=True, timeout=1200, env=_clean_env())
    lines = (done.stdout + done.stderr).splitlines()
    out = "\n".join(line for line in lines if "is ignored: it is neither" not in line)  # this machine's pip config
    assert done.returncode == 0, f"pip install {' '.join(args)} failed in a clean venv:\n{out[-4000:]}"


def test_installed_wheel_runs_a_shipped_scenario_without_the_checkout(wheel: Path, tmp_path: Path) -> None:
    """The README's wheel install in a venv created WITHOUT --system-site-packages, every dependency resolved by
    pip from the registry as pyproject.toml declares it: an import that is not declared fails here even where the
    machine's own Python happens to carry the package (issue 44: `cryptography`). Needs the package registry;
    V2VSIM_SKIP_CLEAN_INSTALL=1 skips it on a machine without one (CI never sets it)."""
    if os.environ.get("V2VSIM_SKIP_CLEAN_INSTALL") == "1":
        pytest.skip("V2VSIM_SKIP_CLEAN_INSTALL=1: the clean install needs the package registry")
    venv = tmp_path / "venv"  # outside the checkout, seeing nothing of this interpreter's packages
    python = _isolated_venv(venv)
    v2vsim = venv / "bin" / "v2vsim"
    _pip_install(python, "torch==2.13.0")
    _pip_install(python, str(wheel))
    work = tmp_path / "work"  # the working directory: neither the checkout nor the venv
    work.mkdir()
    env = _clean_env()

    where = subprocess.run([str(python), "-c", "import json, agents, models, v2vsim; from models import zoo; "
                            "print(json.dumps([agents.__file__, models.__file__, v2vsim.__file__, "
                            "str(zoo.WEIGHTS_DIR)]))"], cwd=work, env=env, capture_output=True, text=True,
                           timeout=300)
    assert where.returncode == 0, where.stderr
    paths = [Path(p) for p in json.loads(where.stdout)]
    for p in paths:  # the wheel's copy, not the checkout's nor a system-wide editable install's
        assert p.resolve().is_relative_to(venv.resolve()), (p, venv)
    weights = paths[-1]

    listed = subprocess.run([str(v2vsim), "scenarios"], cwd=work, env=env, capture_output=True, text=True,
                            timeout=300)
    assert listed.returncode == 0, listed.stderr
    assert {line.split()[0] for line in listed.stdout.splitlines()} == {p.stem for p in
                                                                        (REPO / "scenarios").glob("*.yaml")}

    # by name, with no --out: output.dir (runs/intersection) is relative to the working directory, never the
    # package folder the YAML was found in
    # two CAVs: every method still loads its checkpoint from the installed zoo, with two processes fewer to start
    run = subprocess.run([str(v2vsim), "run", "intersection", "--frames", "2", "--set", "cavs.count=2", "--set",
                          "output.rerun=false"], cwd=work, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-4000:]
    out = work / "runs" / "intersection"
    assert (out / "report.md").is_file()
    package = python.parent.parent / "lib"
    assert not [p for p in package.rglob("runs") if p.is_dir()], "a run wrote into site-packages"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["weights"] == "auto" and metrics["status"] == "complete"
    report = (out / "report.md").read_text()
    assert f"`{weights.parent.parent / 'v2vsim' / 'scenarios' / 'intersection.yaml'}`" in report
    checkpoints = metrics["checkpoints"]
    assert checkpoints and set(checkpoints) == set(metrics["methods"])
    for method, name in checkpoints.items():
        assert name, f"{method} ran untrained: the installed zoo was not found"
        assert (weights / name).is_file(), (method, name)  # the file in the installed package
        assert f"`{name}`" in report
