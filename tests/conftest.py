"""Test-wide settings."""

from __future__ import annotations

import compileall
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]


def pytest_configure(config: pytest.Config) -> None:
    """Byte-compile the checkout once, in the controller, before any worker starts: the suite starts some hundred
    agent processes, and where PYTHONDONTWRITEBYTECODE is set (as on this machine) each of them would compile
    every module of the harness from source again (~0.3 s of CPU a process). And note what the checkout holds
    besides its tracked files, for the guard at the end (pytest_sessionfinish)."""
    if not hasattr(config, "workerinput"):  # not in an xdist worker
        for package in ("v2vsim", "agents", "models"):
            compileall.compile_dir(REPO / package, quiet=1)
        config.stash[_CHECKOUT_BEFORE] = checkout_changes()


# Written by tools, not by the suite's runs: byte code, caches, the editable install's metadata.
_TOOL_DEBRIS = ("__pycache__", ".pytest_cache", ".ruff_cache", ".egg-info")
_CHECKOUT_BEFORE = pytest.StashKey[set[str]]()


def checkout_changes() -> set[str]:
    """`git status` of the checkout, ignored files included, one entry per file: what differs from the last commit
    (tool debris aside). Empty set where this is not a git checkout (a wheel's tests have nothing to guard)."""
    try:
        out = subprocess.run(["git", "status", "--porcelain", "--ignored", "--untracked-files=all", "-z"], cwd=REPO,
                             capture_output=True, check=True, timeout=60).stdout.decode("utf-8", "replace")
    except (OSError, subprocess.SubprocessError):
        return set()
    return {e for e in out.split("\0") if e and not any(d in e for d in _TOOL_DEBRIS)}


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """No test writes into the checkout (issue 52: a SUMO SSM log, ssm_cav0.xml, was once committed at its root):
    a file the suite created, changed or deleted there fails the run, named."""
    config = session.config
    if hasattr(config, "workerinput") or _CHECKOUT_BEFORE not in config.stash:
        return
    stray = sorted(checkout_changes() - config.stash[_CHECKOUT_BEFORE])
    if stray:
        reporter = config.pluginmanager.get_plugin("terminalreporter")
        if reporter is not None:
            reporter.ensure_newline()
            reporter.write_line(f"the suite wrote into the checkout ({len(stray)}; tests must write under tmp_path): "
                                + ", ".join(stray[:20]), red=True)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


# Tests that start real processes or install packages, longest first (pytest --durations). `make test` runs xdist's
# load scheduling with --maxschedchunk 2: each worker takes the next two tests of this order whenever it is free, so
# the long tests run on both workers from the start and the short unit tests fill both at the end. (Without it,
# xdist 3.8 hands each worker a block of ~115 consecutive tests at the start and later blocks of up to half of what
# is left: measured here, one worker ran long tests for 660 s while the other sat idle from 372 s on. --dist
# worksteal would hand the whole first half, i.e. every long test, to one worker.)
_LONG_FIRST = ("tests/test_wheel.py", "tests/agents/test_identity.py", "tests/v2vsim/study/test_sweep.py",
               "tests/agents/test_replay.py", "tests/agents/test_run.py", "tests/agents/test_closed_loop.py",
               "tests/test_fusion_plugin.py", "tests/scripts/", "tests/v2vsim/env/", "tests/v2vsim/comm/test_fuzz.py",
               "tests/v2vsim/training/", "tests/agents/", "tests/models/test_overfit.py",
               "tests/v2vsim/evaluation/test_one_prediction_path.py", "tests/v2vsim/traffic/")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    def rank(item: pytest.Item) -> int:
        path = Path(str(item.path)).relative_to(REPO).as_posix()
        return next((i for i, prefix in enumerate(_LONG_FIRST) if path.startswith(prefix)), len(_LONG_FIRST))

    items.sort(key=rank)  # stable: within a group, the file's own order


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread() -> Iterator[None]:
    """One intra-op thread, as in the agent processes: on 2 shared cores, two OpenMP threads under any
    other load ran ~5x slower."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(autouse=True, scope="session")
def _one_warm_starter() -> Iterator[None]:
    """One warm starter (v2vsim.zygote) per worker for the whole suite, named in V2VSIM_ZYGOTE, as a sweep names
    its own to its runs: every run the suite starts, in this process or as a `v2vsim run` child, forks its agents
    from it instead of importing torch and the harness again in a starter of its own. A fork is a cold start's
    equal to the last digit (tests/v2vsim/test_launch.py); a run that must start cold says so (V2VSIM_START=cold),
    and one on another interpreter or import path starts its own (v2vsim.launch.fits)."""
    from v2vsim.launch import ZYGOTE_ENV, Zygote, start_mode

    if start_mode() == "cold" or os.environ.get(ZYGOTE_ENV):
        yield
        return
    with Zygote() as zygote:
        zygote.wait_ready()
        os.environ[ZYGOTE_ENV] = zygote.path
        try:
            yield
        finally:
            os.environ.pop(ZYGOTE_ENV, None)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory):
    """A recorded dataset of the intersection: 4 training frames (seed 700), 2 validation frames (701)."""
    import io

    from v2vsim.data.record import record_dataset

    root = tmp_path_factory.mktemp("dataset")
    scenario = "scenarios/intersection.yaml"
    record_dataset(scenario, [700], 4, root, split="train", log=io.StringIO())
    record_dataset(scenario, [701], 2, root, split="val", log=io.StringIO())
    return root


class FakeSite:
    """A folder on sys.path where `install` puts a module and a distribution's metadata (.dist-info with entry
    points), as pip would: importlib.metadata finds the entry points there like any installed plugin's."""

    def __init__(self, root) -> None:
        self.root = root
        self.modules: list[str] = []

    def install(self, dist: str, module: str, source: str, entry_points: dict[str, str],
                group: str = "v2vsim.fusion") -> None:
        import importlib

        from models import registry

        (self.root / f"{module}.py").write_text(source)
        info = self.root / f"{dist}-0.1.dist-info"
        info.mkdir()
        (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
        lines = "".join(f"{k} = {v}\n" for k, v in entry_points.items())
        (info / "entry_points.txt").write_text(f"[{group}]\n{lines}")
        self.modules.append(module)
        importlib.invalidate_caches()
        registry.rescan_plugins()  # a process that installed a plugin since it started reads the entry points again


@pytest.fixture
def fake_site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[FakeSite]:
    """Plugins "installed" for one test (FakeSite.install); gone again after it, and the registry forgets them."""
    import sys

    from models import registry

    site = FakeSite(tmp_path_factory.mktemp("site"))
    sys.path.insert(0, str(site.root))
    try:
        yield site
    finally:
        sys.path.remove(str(site.root))
        for m in site.modules:
            sys.modules.pop(m, None)
        registry.rescan_plugins()
