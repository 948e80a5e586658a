"""`v2vsim run` refuses bad input before any process starts: exit 2, one line, no traceback (issue 8)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import pytest

from v2vsim.cli import main

REPO = Path(__file__).resolve().parents[2]
SCENARIO = str(REPO / "scenarios" / "intersection.yaml")


def _one_line_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str], *expect: str) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("v2vsim: error: ") and "Traceback" not in err
    for part in expect:
        assert part in err, err
    return err


@pytest.mark.parametrize(("args", "expect"), [
    (["--frames", "0"], ["--frames 0", ">= 1"]),
    (["--frames", "-1"], ["--frames -1", ">= 1"]),
    (["--set", "duration_s=.inf"], ["duration_s", "finite"]),
    (["--set", "duration_s=.nan"], ["duration_s", "finite"]),
    (["--set", "seed=2147483648"], ["seed", "0..2147483647"]),
    (["--set", "seed=-5"], ["seed", "0..2147483647"]),
    (["--set", "transport.listen=[tcp/127.0.0.1:70000]"], ["transport.listen[0]", "1..65535"]),
    (["--set", "transport.lost_after_s=0"], ["transport.lost_after_s", "seconds > 0"]),
    (["--set", "transport.lost_after_s=.inf"], ["transport.lost_after_s"]),
    (["--set", "cavs.ego=[cav9]"], ["cavs.ego[0]", "'cav9'", "cav0, cav1, cav2, cav3"]),
    (["--set", "cavs.ego=[cav0,cav0]"], ["cavs.ego[1]", "listed twice"]),
    (["--run-id", "a/b"], ["--run-id"]),
    # a ratio without a trained compressor in the zoo: refused (naming the command that trains it), not run with a
    # random one behind trained models
    (["--set", "comm.channel_compression=2"], ["comm.channel_compression: 2", "no trained compressor for ratio 2",
                                               "--stage compress --ratios 2"]),
    # a ratio whose compressor is trained but whose fusion models were trained on another wire: refused too
    (["--set", "comm.channel_compression=16"], ["comm.channel_compression: 16", "trained on the ratio-8 wire",
                                                "--wire-ratio 16"]),
    (["--set", "comm.fusion_deadline_ms=100"], ["comm.fusion_deadline_ms", "less than one frame"]),
    # a relative perception.weights is resolved against the scenario's folder: the error says so
    (["--set", "perception.weights=my_zoo"], ["perception.weights", "resolved against the scenario's folder",
                                              "absolute path"]),
    # an empty --methods used to run all eight methods, exit 0; ",," was echoed as perception.methods=[,,]
    (["--methods", ""], ["--methods ''", "names no method", "none,cobevt"]),
    (["--methods", ",,"], ["--methods ',,'", "names no method"]),
])
def test_run_refuses_bad_arguments(args: list[str], expect: list[str], tmp_path: Path,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    _one_line_exit_2(["run", SCENARIO, "--out", str(tmp_path / "out"), *args], capsys, *expect)


def test_run_refuses_an_out_that_is_a_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "taken"
    f.write_text("x")
    _one_line_exit_2(["run", SCENARIO, "--out", str(f)], capsys, "--out", str(f), "not a directory")
    _one_line_exit_2(["run", SCENARIO, "--out", str(f / "sub")], capsys, "--out", "cannot write there")


def test_run_refuses_an_out_under_proc(capsys: pytest.CaptureFixture[str]) -> None:
    _one_line_exit_2(["run", SCENARIO, "--out", "/proc/v2vsim-run"], capsys, "--out /proc/v2vsim-run")
    _one_line_exit_2(["run", SCENARIO, "--out", "/proc/self"], capsys, "--out /proc/self", "cannot write there")


def test_run_refuses_an_unwritable_out(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An existing directory nobody may write into, for root too (issue 52: this test used to skip as root, i.e. in
    every CI run): one of sysfs (the kernel refuses new files there to root), and one with mode 0555, checked by a
    process that is not root (as root: a forked child that dropped to nobody)."""
    _one_line_exit_2(["run", SCENARIO, "--out", "/sys/kernel"], capsys, "--out /sys/kernel", "cannot write there")
    parent = Path(tempfile.mkdtemp(prefix="v2vsim-locked-"))  # /tmp: nobody may reach it (tmp_path is root's 0700)
    try:
        parent.chmod(0o755)
        locked = parent / "locked"
        locked.mkdir()
        locked.chmod(0o555)
        if os.geteuid() != 0:
            _one_line_exit_2(["run", SCENARIO, "--out", str(locked)], capsys, "cannot write there")
        else:
            assert _as_nobody(lambda: _refused(locked)) == 0
    finally:
        locked.chmod(0o755)
        shutil.rmtree(parent)


def _refused(out: Path) -> int:
    """0 when check_output_dir (what `run --out` calls first) refuses `out` as unwritable, 1 otherwise."""
    from v2vsim.config import ConfigError, check_output_dir

    try:
        check_output_dir(out, "--out")
    except ConfigError as e:
        return 0 if f"--out {out}: cannot write there: permission denied" in str(e) else 1
    return 1


def _as_nobody(fn: Callable[[], int]) -> int:
    """fn's result, run in a forked child that dropped root for nobody (65534): root passes every permission check."""
    pid = os.fork()
    if pid == 0:  # the child: no return, no exception out of here
        code = 3
        try:
            os.setgroups([])
            os.setgid(65534)
            os.setuid(65534)
            code = fn()
        finally:
            os._exit(code)
    return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])


def test_run_refuses_an_output_dir_from_the_scenario(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "taken"
    f.write_text("x")
    _one_line_exit_2(["run", SCENARIO, "--set", f"output.dir={f}"], capsys, "output.dir", "not a directory")


@pytest.mark.parametrize("content", [b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff", b"\xff\xfe\x00s\x00e\x00e\x00d"])
def test_binary_scenario_exits_2_from_the_real_command(tmp_path: Path, content: bytes) -> None:
    p = tmp_path / "s.yaml"
    p.write_bytes(content)
    r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "run", str(p), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert "not a text (UTF-8) file" in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_view_without_a_recording_is_a_clear_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["view", str(tmp_path / "nowhere")]) == 2
    assert "no such run directory" in capsys.readouterr().err
    assert main(["view", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "no recording.rrd" in err and "output.rerun: false" in err
    (tmp_path / "recording.rrd").write_bytes(b"")
    assert main(["view", str(tmp_path), "--screenshots", str(tmp_path / "s"), "--at", "1,x"]) == 2
    assert "--at" in capsys.readouterr().err


def test_view_without_a_display_says_how_to_look_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "recording.rrd").write_bytes(b"")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["view", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("v2vsim view: error: no display here") and "\n" not in err
    assert f"rerun {tmp_path / 'recording.rrd'}" in err and "--screenshots" in err


def test_view_screenshots_without_vulkan_is_one_line_naming_what_to_install(tmp_path: Path) -> None:
    """issue 52 item 1: the headless viewer panicked with a Rust backtrace where no Vulkan driver is installed. The
    missing driver is simulated by naming one that does not exist (VK_DRIVER_FILES: the loader looks nowhere else);
    a machine without the loader itself gets the same line."""
    (tmp_path / "recording.rrd").write_bytes(b"")
    env = dict(os.environ, VK_DRIVER_FILES=str(tmp_path / "no_such_icd.json"))
    r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "view", str(tmp_path), "--screenshots",
                        str(tmp_path / "shots")], capture_output=True, text=True, timeout=120, env=env)
    err = r.stderr.strip()
    assert r.returncode == 2 and "\n" not in err, r.stderr
    assert err.startswith("v2vsim view: error: the Rerun viewer renders with Vulkan") and "panicked" not in err
    assert "apt-get install -y mesa-vulkan-drivers" in err
    assert "no Vulkan loader" in err or "no_such_icd.json" in err


@pytest.mark.parametrize("where", ["under_a_file", "/proc/v2vsim-shots", "/sys/v2vsim-shots"])
def test_view_screenshots_into_an_unwritable_place_is_one_line(tmp_path: Path, where: str,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "recording.rrd").write_bytes(b"")
    (tmp_path / "a_file").write_text("x")
    out = str(tmp_path / "a_file" / "shots") if where == "under_a_file" else where
    assert main(["view", str(tmp_path), "--screenshots", out]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"v2vsim view: error: --screenshots {out}: cannot write there") and "\n" not in err
    assert main(["view", str(tmp_path), "--screenshots", str(tmp_path / "a_file")]) == 2
    assert "is a file, not a directory" in capsys.readouterr().err


def test_sigint_stops_a_verb_started_with_sigint_ignored() -> None:
    """`cmd &` in a shell without job control starts cmd with SIGINT ignored; Ctrl-C (the runner's
    SIGINT, a test's) must still stop every verb."""
    import signal
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "v2vsim.cli", "router", "--listen", f"tcp/127.0.0.1:{port}"],
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        assert "listening" in proc.stderr.readline()  # type: ignore[union-attr]
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=15) != 0
    finally:
        proc.kill()


def test_sweep_refuses_an_empty_methods(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _one_line_exit_2(["sweep", SCENARIO, "--seeds", "0", "--methods", " , ", "--out", str(tmp_path / "s")], capsys,
                     "--methods ' , '", "names no method")
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("argv", [
    ["run", "{name}", "--out", "{out}"],
    ["frame", "{name}", "--at", "0", "--out", "{out}"],
    ["dataset", "{name}", "--seeds", "0", "--frames", "1", "--out", "{out}"],
    ["sweep", "{name}", "--seeds", "0", "--out", "{out}"],
    ["bandwidth", "{name}", "--seeds", "0", "--out", "{out}"],
    ["agent", "{name}", "--cav", "cav0", "--run-id", "r", "--cavs", "cav0", "--egos", "cav0"],
], ids=lambda argv: argv[0])
def test_every_scenario_verb_refuses_an_unknown_name_listing_the_shipped_ones(
        argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """SCENARIO is found in one place (v2vsim.config.find_scenario), so every verb says the same thing."""
    out = tmp_path / "out"
    shipped = ", ".join(sorted(p.stem for p in (REPO / "scenarios").glob("*.yaml")))
    _one_line_exit_2([a.format(name="no_such_scenario", out=out) for a in argv], capsys,
                     "no_such_scenario: scenario file not found", f"shipped: {shipped}")


def test_scenarios_lists_every_shipped_scenario_with_its_description(tmp_path: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "scenarios"], cwd=tmp_path, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    names = sorted(p.stem for p in (REPO / "scenarios").glob("*.yaml"))
    assert [line.split()[0] for line in lines] == names
    assert all(len(line.split()) > 3 for line in lines), r.stdout  # a description after each name
    assert "Four-way signalised intersection" in lines[names.index("intersection")]
