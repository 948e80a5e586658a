"""The runner and the driver without real processes: the one progress display, the driver stopping
when nobody fuses any more, ports of one plan, and what the runner says at the end (issue 8)."""

from __future__ import annotations

import io
import json
import signal
from collections.abc import Callable
from pathlib import Path

import pytest

import agents.driver as driver
import v2vsim.runner as runner
from agents.args import AgentArgs
from agents.progress import ENV, ProgressDisplay, parse_record, report_progress
from v2vsim.comm.transport import free_ports
from v2vsim.config import load_scenario

REPO = Path(__file__).resolve().parents[2]
SCENARIO = REPO / "scenarios" / "intersection.yaml"


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _ego(frame: int, total: int, delivered: int = 0, dropped: int = 0, out_of_range: int = 0) -> dict:
    return {"who": "ego.cav0", "frame": frame, "total": total, "delivered": delivered, "dropped": dropped,
            "out_of_range": out_of_range}


def test_plain_progress_lines_every_n_frames_when_not_a_terminal() -> None:
    out, clock = io.StringIO(), Clock()
    d = ProgressDisplay(60, 10.0, ["ego.cav0"], out, tty=False, clock=clock)
    assert d.every == 6  # 10 % of the run
    d.record("driver", {"frame": 0, "total": 60})
    for k in range(1, 61):
        clock.t += 0.5  # 2 frames/s at 10 Hz: 0.2x real time
        d.record("driver", {"frame": k, "total": 60})
        d.record("ego.cav0", _ego(k, 60, delivered=2 * k, dropped=k // 10, out_of_range=1))
        if k == 7:
            d.message("v2vsim-ego: CAV cav2 is gone at frame 7; fusing the others")
    lines = out.getvalue().splitlines()
    progress = [ln for ln in lines if ln.startswith("v2vsim: frame ")]
    assert [ln.split()[2] for ln in progress] == [f"{k}/60" for k in range(6, 61, 6)]
    assert lines[1].startswith("v2vsim-ego: CAV cav2 is gone")  # a child's line, on its own line
    assert progress[-1] == ("v2vsim: frame 60/60 (100%)  2.0 frames/s  0.20x real time  "
                            "V2V 120 delivered, 6 dropped, 1 out of range  ETA 0 s")
    assert "ETA 27 s" in progress[0]  # 54 frames left at 2 frames/s
    assert "\r" not in out.getvalue()


def test_the_run_is_as_far_as_its_slowest_ego() -> None:
    out = io.StringIO()
    d = ProgressDisplay(4, 10.0, ["ego.cav0", "ego.cav1"], out, tty=False, clock=Clock())
    d.record("ego.cav0", _ego(3, 4, delivered=3))
    assert d.done == 0 and out.getvalue() == ""
    d.record("ego.cav1", {**_ego(2, 4, delivered=2), "who": "ego.cav1"})
    assert d.done == 2 and "V2V 5 delivered" in out.getvalue()


def test_live_line_on_a_terminal_keeps_child_lines_whole() -> None:
    out, clock = io.StringIO(), Clock()
    d = ProgressDisplay(10, 10.0, ["ego.cav0"], out, tty=True, clock=clock)
    d.record("driver", {"frame": 0, "total": 10})
    clock.t += 1
    d.record("ego.cav0", _ego(1, 10))
    d.message("[ego.cav0] Traceback (most recent call last):")
    clock.t += 1
    d.record("ego.cav0", _ego(10, 10))
    d.close()
    text = out.getvalue()
    assert text.startswith("\r\x1b[Kv2vsim: frame 0/10")  # drawn as soon as the driver starts
    assert "\r\x1b[Kv2vsim: frame 1/10" in text
    # the live line is wiped, the child's line printed whole, and the live line drawn again below it
    assert "\r\x1b[K[ego.cav0] Traceback (most recent call last):\n\r\x1b[Kv2vsim: frame 1/10" in text
    assert text.endswith("v2vsim: frame 10/10 (100%)  5.0 frames/s  0.50x real time  V2V 0 delivered, 0 dropped, "
                         "0 out of range  ETA 0 s\n")


def test_progress_records_round_trip(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv(ENV, "records")
    report_progress("ego.cav0", 5, 20, delivered=9, dropped=1, out_of_range=0)
    line = capsys.readouterr().err
    assert line.endswith("\n") and line.count("\n") == 1
    assert parse_record(line.rstrip("\n")) == {"who": "ego.cav0", "frame": 5, "total": 20, "delivered": 9,
                                               "dropped": 1, "out_of_range": 0}
    assert parse_record("[ego cav0] frame 5/20") is None and parse_record("@progress {not json") is None
    monkeypatch.delenv(ENV)  # an agent started by hand: a human line every 20 frames
    report_progress("driver", 19, 40)
    report_progress("driver", 20, 40)
    assert capsys.readouterr().err.startswith("[driver] frame 20/40")


def test_ports_of_one_plan_are_distinct() -> None:
    for _ in range(20):
        ports = free_ports(18)
        assert len(set(ports)) == 18
    sc = load_scenario(SCENARIO, ["cavs.count=16", "cavs.ego=all"])
    names = ["driver.main"] + [f"cav.cav{i}" for i in range(16)] + [f"ego.cav{i}" for i in range(16)]
    plan = runner.plan_endpoints(sc, names)
    assert len(set(plan.values())) == len(names)


def test_how_a_child_ended_is_said_plainly() -> None:
    assert runner._describe("driver.main", -9) == "the simulator driver died (signal 9, SIGKILL)"
    assert runner._describe("ego.cav0", 128 + 15) == "ego.cav0 was stopped (signal 15, SIGTERM)"
    assert runner._describe("ego.cav0", 1) == "ego.cav0 exited with code 1"


def test_done_is_said_only_when_the_report_exists(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """issue 8 item 7: an ego that wrote nothing must not end in "done: .../report.md"."""
    sc = load_scenario(SCENARIO)
    monkeypatch.setattr(runner, "_start", lambda children, *a: None)
    monkeypatch.setattr(runner, "_watch", lambda children, display, failures: 0)
    assert runner.run(sc, tmp_path, frames=2) == 1
    err = capsys.readouterr().err
    assert "v2vsim: done" not in err and f"no report was written to {tmp_path}" in err
    (tmp_path / "report.md").write_text("# report\n")
    (tmp_path / "metrics.json").write_text('{"status": "complete"}')
    assert runner.run(sc, tmp_path, frames=2) == 0
    assert f"v2vsim: done: {tmp_path / 'report.md'}" in capsys.readouterr().err
    # issue 45: the last line says what metrics.json says (a degraded run still exits 0: its files are there)
    (tmp_path / "metrics.json").write_text('{"status": "degraded: cav1 lost from frame 1"}')
    assert runner.run(sc, tmp_path, frames=2) == 0
    assert ("v2vsim: done, not complete: degraded: cav1 lost from frame 1; report: "
            f"{tmp_path / 'report.md'}") in capsys.readouterr().err


# ---- the driver stops when every ego is gone ---------------------------------------------------


class FakeBackend:
    static = object()

    def reset(self) -> object:
        return object()

    def step(self) -> object:
        return object()

    def close(self) -> None:
        pass


class FakeBus:
    """Acks every world until the only ego dies after frame `ego_dies_after`."""

    def __init__(self, ego_dies_after: int) -> None:
        self.ego_dies_after = ego_dies_after
        self.worlds = 0
        self.kinds: list[str] = []
        self.ego_alive = True
        self.on_ack: Callable[[str, bytes], None] | None = None

    def serve(self, kind: str, data: bytes) -> None:
        pass

    def subscribe(self, kind: str, callback: Callable[[str, bytes], None]) -> None:
        if kind == "ack":
            self.on_ack = callback

    def ready(self) -> None:
        pass

    def wait_alive(self, names: object, timeout_s: float) -> None:
        pass

    def is_alive(self, who: str) -> bool:
        return who != "ego.cav0" or self.ego_alive

    def control_rejections(self) -> dict[tuple[str, str], int]:
        return {}

    def leave_word(self, **doc: object) -> None:
        self.word = doc

    def put(self, kind: str, data: bytes) -> int:
        self.kinds.append(kind)
        if kind == "world":
            k = self.worlds
            self.worlds += 1
            if k >= self.ego_dies_after:
                self.ego_alive = False
            elif self.on_ack is not None:
                self.on_ack("cav0", json.dumps({"ego": "cav0", "frame": k}).encode())
        return len(data)


@pytest.mark.parametrize("clock", ["lockstep", "realtime"])
def test_driver_stops_when_every_ego_is_gone(clock: str, monkeypatch: pytest.MonkeyPatch,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    sc = load_scenario(SCENARIO, [f"transport.clock={clock}", "rate_hz=1000", "cavs.count=2"])
    monkeypatch.setattr(driver, "make_backend", lambda sc, **kw: FakeBackend())
    monkeypatch.setattr(driver, "static_to_bytes", lambda static: b"static")
    monkeypatch.setattr(driver, "world_to_bytes", lambda world: b"world")
    args = AgentArgs(scenario=sc, scenario_path=str(SCENARIO), overrides=(), run_id="r1", listen="", peers=(),
                     cavs=("cav0", "cav1"), egos=("cav0",), cav="", frames=500, out="")
    bus = FakeBus(ego_dies_after=3)
    assert driver.drive(args, bus) == 1  # type: ignore[arg-type]
    assert bus.worlds == 4 and "done" not in bus.kinds  # frames 0..3 went out; the ego died with frame 3
    assert bus.word == {"control_rejections": {}}  # what its bye carries (open loop: no SSM conflicts)
    assert "every ego process is gone at frame 4" in capsys.readouterr().err
    full = FakeBus(ego_dies_after=10**9)
    assert driver.drive(dataclasses_replace(args, frames=6), full) == 0  # type: ignore[arg-type]
    assert full.worlds == 6 and full.kinds[-1] == "done"


def dataclasses_replace(args: AgentArgs, **kw: object) -> AgentArgs:
    import dataclasses

    return dataclasses.replace(args, **kw)  # type: ignore[arg-type]


def test_sigterm_name_known() -> None:
    assert runner._signame(int(signal.SIGTERM)) == ", SIGTERM" and runner._signame(99) == ""
