"""The warm starter (v2vsim.zygote, v2vsim.launch): a forked process behaves as a cold one (exit codes, signals,
stdin, stdout, environment, working directory), dies with its requester, and a warm run's results are a cold run's
to the last digit."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from v2vsim.config import ConfigError
from v2vsim.launch import MODE_ENV, ZYGOTE_ENV, Launcher, Zygote, fits, launcher, start_mode, zygote_identity

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the warm starter forks (Linux)")


@pytest.fixture(scope="module")
def warm() -> Iterator[Launcher]:
    z = Zygote()
    launch = Launcher(z.path, owned=z)
    yield launch
    launch.close()


def _py(launch: Launcher, code: str, **kw: object) -> object:
    """Start `code` warm, through tests/v2vsim/launch_probe.py."""
    return launch.start("tests.v2vsim.launch_probe", [code], dict(os.environ, PYTHONPATH=str(REPO)), **kw)


def test_a_forked_process_is_a_cold_one(warm: Launcher, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # the requester's working directory goes with the request
    p = _py(warm, "import os, sys; print(os.getcwd(), sys.stdin.read()); "
                  "print(os.getpgid(0) == os.getpid(), file=sys.stderr); sys.exit(3)", stdin_pipe=True)
    assert p.stdin is not None
    p.stdin.write(b"from stdin")
    p.stdin.close()
    assert p.stdout is not None
    out = p.stdout.read().decode()
    assert p.wait(timeout=30) == 3
    assert "from stdin" in out and str(tmp_path) in out and "True" in out  # its own process group


def test_the_environment_is_the_requesters(warm: Launcher) -> None:
    p = warm.start("tests.v2vsim.launch_probe", ["import os; print(os.environ.get('PROBE'))"],
                   dict(os.environ, PROBE="seen", PYTHONPATH=str(REPO)))
    assert p.stdout is not None and p.stdout.read().decode().strip() == "seen" and p.wait(timeout=30) == 0


def test_a_request_on_another_import_path_starts_cold(warm: Launcher, tmp_path: Path) -> None:
    # a fork keeps the zygote's sys.path: a PYTHONPATH entry it lacks (a plugin's folder) needs a cold start
    (tmp_path / "only_here.py").write_text("WHERE = 'tmp'\n")
    p = warm.start("tests.v2vsim.launch_probe", ["import only_here; print(only_here.WHERE)"],
                   dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(tmp_path)])))
    assert p.stdout is not None and p.stdout.read().decode().strip() == "tmp" and p.wait(timeout=60) == 0
    assert not fits(zygote_identity(warm.path or ""), {"PYTHONPATH": str(tmp_path)})
    assert fits(zygote_identity(warm.path or ""), {"PYTHONPATH": str(REPO)})
    # a venv's python is a link to the base interpreter: its prefix tells them apart (tests/test_fusion_plugin.py)
    assert not fits({**zygote_identity(warm.path or ""), "prefix": "/a/venv"}, {"PYTHONPATH": str(REPO)})


def test_signals_and_crashes_end_it_as_they_end_a_cold_process(warm: Launcher) -> None:
    p = _py(warm, "import time; time.sleep(60)")
    time.sleep(0.5)
    os.killpg(p.pid, signal.SIGKILL)
    assert p.wait(timeout=30) == -signal.SIGKILL
    p = _py(warm, "raise RuntimeError('boom')")
    assert p.stdout is not None and "RuntimeError: boom" in p.stdout.read().decode()
    assert p.wait(timeout=30) == 1


def test_into_a_log_file(warm: Launcher, tmp_path: Path) -> None:
    log = tmp_path / "log"
    with open(log, "wb") as f:
        p = _py(warm, "import sys; print('out'); print('err', file=sys.stderr)", stdout=f)
    assert p.wait(timeout=30) == 0 and p.stdout is None
    assert log.read_text().split() == ["out", "err"]


def test_a_requester_that_dies_takes_its_processes(warm: Launcher, tmp_path: Path) -> None:
    pidfile = tmp_path / "pid"
    # a requester of its own (connected to the same zygote) that starts a sleeper, then is killed
    code = ("import os, sys, time; from v2vsim.launch import launcher; l = launcher(); "
            "p = l.start('tests.v2vsim.launch_probe', ['import time; time.sleep(120)'], dict(os.environ)); "
            f"open({str(pidfile)!r}, 'w').write(str(p.pid)); time.sleep(120)")
    req = subprocess.Popen([sys.executable, "-c", code], env=dict(os.environ, PYTHONPATH=str(REPO),
                                                                   **{ZYGOTE_ENV: warm.path or ""}))
    deadline = time.monotonic() + 60
    while not (pidfile.exists() and pidfile.read_text()) and time.monotonic() < deadline:
        time.sleep(0.1)
    sleeper = int(pidfile.read_text())
    os.kill(sleeper, 0)  # alive
    req.kill()
    req.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(sleeper, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        pytest.fail("the sleeper outlived the requester that asked for it")


def test_the_mode_is_checked() -> None:
    assert start_mode({MODE_ENV: "cold"}) == "cold" and start_mode({}) == "warm"
    with pytest.raises(ConfigError, match="V2VSIM_START='tepid'"):
        start_mode({MODE_ENV: "tepid"})
    assert not launcher({MODE_ENV: "cold"}).warm


def _metrics_without_timing(out: Path) -> dict:
    doc = json.loads((out / "metrics.json").read_text())
    for k in ("timing", "wall_s", "real_time_factor"):
        doc.pop(k, None)
    for m in doc["methods"].values():
        m.pop("fusion_ms", None)
    return doc


def test_a_warm_run_is_a_cold_run_to_the_last_digit(tmp_path: Path) -> None:
    """The same point cold and warm: every result in metrics.json equal (the wall-clock timings aside)."""
    outs = {}
    for mode in ("cold", "warm"):
        outs[mode] = tmp_path / mode
        env = {k: v for k, v in os.environ.items() if k != ZYGOTE_ENV}
        r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "run", str(REPO / "scenarios" / "intersection.yaml"),
                            "--frames", "4", "--out", str(outs[mode]), "--set", "output.rerun=false",
                            "--set", "perception.methods=[none, late, cobevt]"],
                           env={**env, MODE_ENV: mode}, cwd=REPO, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
    cold, warm = (_metrics_without_timing(outs[m]) for m in ("cold", "warm"))
    assert cold["methods"]["cobevt"]["iou_vehicle"] is not None
    assert warm == cold
