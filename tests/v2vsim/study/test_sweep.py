"""`v2vsim sweep`: grid parsing and validation, the paired design and resumability (with fake runs), the
two-level bootstrap's coverage, per-frame values from a recording, and one real two-point sweep."""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from v2vsim.cli import main
from v2vsim.config import ConfigError, parse_override
from v2vsim.study import plan as plan_mod
from v2vsim.study import runs as runs_mod
from v2vsim.study.grid import base_overrides, parse_axes, parse_axis, parse_seeds, split_values
from v2vsim.study.stats import interval, paired_clusters
from v2vsim.study.sweep import SweepArgs, prepare, sweep

REPO = Path(__file__).resolve().parents[3]
SCENARIO = REPO / "scenarios" / "intersection.yaml"
CONTRACT_METRICS = ["iou_vehicle", "iou_vehicle_frame_mean", "iou_road", "iou_lane", "ap50", "ap70", "fusion_ms",
                    "bytes_per_frame"]


# ---- grid and seeds ------------------------------------------------------------------------------------


def test_grid_values_are_parsed_exactly_like_set() -> None:
    assert split_values("0, 0.5,[none, cobevt],{a: 1, b: 2},'x,y'") == ["0", "0.5", "[none, cobevt]",
                                                                       "{a: 1, b: 2}", "'x,y'"]
    axis = parse_axis("comm.latency_ms.mean=0,50,1e2,null")
    assert axis.key == "comm.latency_ms.mean" and axis.texts == ("0", "50", "1e2", "null")
    assert list(axis.values) == [parse_override(f"k={t}")[1] for t in axis.texts]
    assert parse_axis("perception.methods=[none, cobevt],[none]").values == (["none", "cobevt"], ["none"])
    assert parse_axis("comm.drop.p=0,0.5").numeric and not parse_axis("output.rerun=true,false").numeric


@pytest.mark.parametrize("text, expect", [
    ("comm.drop.p", "expected KEY.PATH=V1,V2"), ("comm.drop.p=", "expected KEY.PATH=V1,V2"),
    ("comm.drop.p=0,,1", "empty value"), ("comm.drop.p=0,0", "listed twice"),
    ("comm..p=0", "bad key path"), ("seed=1,2", "use --seeds"), ("comm.drop.p=[0", "not valid YAML"),
])
def test_bad_grid_options_are_named(text: str, expect: str) -> None:
    with pytest.raises(ConfigError, match="--grid") as e:
        parse_axis(text)
    assert expect in str(e.value)


def test_seeds() -> None:
    assert parse_seeds("0-3") == [0, 1, 2, 3] and parse_seeds("7") == [7] and parse_seeds(" 2 - 2 ") == [2]
    for bad in ("3-1", "a", "-1", "1,2", ""):
        with pytest.raises(ConfigError, match="--seeds"):
            parse_seeds(bad)


def _exit_2(argv: list[str], capsys: pytest.CaptureFixture[str], *expect: str) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    for e in expect:
        assert e in err, err


def test_a_bad_key_or_value_exits_2_naming_it_before_anything_runs(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sweep"
    base = ["sweep", str(SCENARIO), "--seeds", "0-1", "--out", str(out)]
    _exit_2([*base, "--grid", "comm.drop.p=0,0.5", "--grid", "comm.dorp.p=0,0.5"], capsys, "comm.dorp",
            "unknown key", "did you mean 'drop'")
    _exit_2([*base, "--grid", "comm.drop.p=0,1.5"], capsys, "comm.drop.p", "1.5", "0..1")  # the 2nd point only
    _exit_2([*base, "--grid", "comm.drop.p=0", "--set", "comm.drop.p=0.2"], capsys, "also swept by --grid")
    _exit_2([*base, "--grid", "comm.drop.p=0", "--grid", "comm.drop.p=1"], capsys, "given twice")
    _exit_2([*base, "--grid", "comm.drop.p=0", "--set", "seed=3"], capsys, "use --seeds")
    _exit_2([*base, "--grid", "comm.drop.p=0", "--frames", "0"], capsys, "--frames 0")
    _exit_2([*base, "--grid", "comm.drop.p=0", "--methods", "none,cobev"], capsys, "perception.methods")
    assert not (out / "runs").exists()


# ---- the design and resumability, with the run step replaced by a fake ------------------------------------


def test_cartesian_product_with_the_same_seeds_at_every_point(tmp_path: Path) -> None:
    d = prepare(SweepArgs(SCENARIO, ("comm.drop.p=0,0.5", "comm.latency_ms.mean=0,50,100"), "3-4", tmp_path,
                          frames=2, overrides=("cavs.count=2",), methods="none,cobevt", replay=False))
    assert len(d.points) == 6 and len({p.pid for p in d.points}) == 6
    assert [p.texts for p in d.points][:3] == [("0", "0"), ("0", "50"), ("0", "100")]  # last key fastest
    assert len(d.specs) == 12 and len({s.out for s in d.specs}) == 12
    for p in d.points:
        specs = [s for s in d.specs if s.point == p]
        assert [s.seed for s in specs] == [3, 4]  # paired: every point has the same seeds
        for s in specs:
            assert s.request["overrides"][:3] == [f"seed={s.seed}", f"comm.drop.p={p.texts[0]}",
                                                  f"comm.latency_ms.mean={p.texts[1]}"]
            assert s.request["config"]["seed"] == s.seed and s.request["config"]["output"]["rerun"] is False
            argv = s.argv(d.scenario)
            assert argv[:3] == ["-m", "v2vsim.cli", "run"] and argv[-2:] == ["--frames", "2"]
    assert base_overrides([], ["output.rerun=true"], None) == ["output.rerun=true"]  # the user's say wins
    assert base_overrides(parse_axes(["output.rerun=true,false"]), [], None) == []
    assert base_overrides([], [], "none,late") == ["output.rerun=false", "perception.methods=[none,late]"]


def _fake_metrics(spec: plan_mod.RunSpec) -> dict:
    p = float(spec.point.texts[0]) if spec.point.texts else 0.5  # comm.drop.p
    methods = {}
    for i, m in enumerate(("none", "attfuse", "cobevt")):
        iou = 0.4 + 0.1 * i * (1 - p) + 0.01 * spec.seed
        methods[m] = {"iou_vehicle": iou, "iou_vehicle_frame_mean": iou - 0.01, "iou_road": 0.7, "iou_lane": None,
                      "ap50": iou + 0.2, "ap70": iou, "fusion_ms": 1.0 + i, "bytes_per_frame": 1000 * i,
                      "frames": 2, "iou_vehicle_all": iou - 0.05}
    return {"scenario": "intersection", "frames": 2, "status": "complete", "methods": methods}


class FakeJob:
    """A run that has finished by the time it is polled: writes what `v2vsim run` would (replays started
    together: what each would)."""

    def __init__(self, spec: plan_mod.RunSpec, code: int = 0, status: str = "complete") -> None:
        self.code = code
        self.interrupted = False
        for other in spec.together:
            other.out.joinpath("metrics.json").write_text(json.dumps(_fake_metrics(other) | {"status": "complete"}))
        (spec.out / runs_mod.LOG).write_text("v2vsim: run abc: 2 CAVs\nTraceback ...\nValueError: boom\n"
                                             if code else "v2vsim: done\n")
        if status:
            spec.out.joinpath("metrics.json").write_text(json.dumps(_fake_metrics(spec) | {"status": status}))
        if spec.records and status == "complete":  # what output.record_messages leaves (header and map)
            (spec.out / "messages").mkdir(exist_ok=True)
            (spec.out / "messages" / "header.json").write_text(json.dumps(
                {"format": "v2vsim.messages", "version": 1, "chunks": [], "status": "complete"}))
            (spec.out / "messages" / "static.bin").write_bytes(b"")

    def poll(self) -> int | None:
        return self.code

    def interrupt(self) -> None:
        self.interrupted = True

    def kill(self) -> None:
        pass


class FakeStarter:
    def __init__(self, fail: set[tuple[str, int]] = frozenset(), partial: set[tuple[str, int]] = frozenset(),
                 interrupt_at: int | None = None) -> None:
        self.started: list[tuple[str, int]] = []
        self.fail, self.partial, self.interrupt_at = fail, partial, interrupt_at

    def __call__(self, spec: plan_mod.RunSpec) -> FakeJob:
        key = (spec.point.texts[0] if spec.point.texts else "", spec.seed)
        if self.interrupt_at is not None and len(self.started) == self.interrupt_at:
            raise KeyboardInterrupt
        self.started.append(key)
        self.started += [(s.point.texts[0] if s.point.texts else "", s.seed) for s in spec.together]
        if key in self.fail:
            return FakeJob(spec, code=1, status="")
        return FakeJob(spec, status="interrupted after 1 frames" if key in self.partial else "complete")


def _args(out: Path, *extra: str, grid: tuple[str, ...] = ("comm.drop.p=0,0.5",), seeds: str = "0-2",
          bootstrap: int = 200, replay: bool = False) -> SweepArgs:
    """Every run simulated unless `replay` (the replay tests below)."""
    return SweepArgs(SCENARIO, grid, seeds, out, frames=2, overrides=("cavs.count=2", *extra), bootstrap=bootstrap,
                     replay=replay)


def _csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_fake_sweep_resumes_reruns_what_is_not_complete_and_reports_failures(tmp_path: Path,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    import io

    from v2vsim.study import plots

    monkeypatch.setattr(runs_mod.time, "sleep", lambda s: None)
    real_plot_all = plots.plot_all
    monkeypatch.setattr(plots, "plot_all", lambda *a, **k: [])  # plotted in the last sweep only (time)
    out = tmp_path / "sweep"
    start = FakeStarter(fail={("0.5", 1)}, partial={("0", 2)})
    log = io.StringIO()
    assert sweep(_args(out), start=start, stream=log) == 1  # one run failed: exit 1, the others went on
    assert len(start.started) == 6
    text = log.getvalue()
    assert "[comm.drop.p=0.5] seed 1 failed (exit code 1, no metrics.json)" in text and "ValueError: boom" in text
    assert "[comm.drop.p=0] seed 2 failed (exit code 0, status 'interrupted after 1 frames')" in text
    assert "v2vsim sweep: 6/6 runs (2 failed), 0 running" in text and "ETA" in text
    rows = _csv(out / "sweep.csv")
    assert list(rows[0])[:3 + len(CONTRACT_METRICS)] == ["comm.drop.p", "seed", "method", *CONTRACT_METRICS]
    assert list(rows[0])[-1] == "status" and {r["status"] for r in rows} == {"complete"}  # added after the contract's
    assert len(rows) == 4 * 3  # 4 complete runs x 3 methods
    doc = json.loads((out / "sweep.json").read_text())
    assert sorted((f["point"], f["seed"], f["code"]) for f in doc["runs"]["failed"]) == [
        ("comm.drop.p=0", 2, 0), ("comm.drop.p=0.5", 1, 1)]

    # resumed: only the two that did not complete run again; complete ones are reused
    start2 = FakeStarter()
    log = io.StringIO()
    assert sweep(_args(out), start=start2, stream=log) == 0
    assert sorted(start2.started) == [("0", 2), ("0.5", 1)]
    assert "4 reused" in log.getvalue()
    rows = _csv(out / "sweep.csv")
    assert len(rows) == 6 * 3
    assert [(r["comm.drop.p"], r["seed"]) for r in rows[::3]] == [("0", "0"), ("0", "1"), ("0", "2"),
                                                                  ("0.5", "0"), ("0.5", "1"), ("0.5", "2")]
    # the same settings spelled otherwise: nothing reruns; other settings: everything does
    start3 = FakeStarter()
    assert sweep(_args(out, "output.rerun=false"), start=start3, stream=io.StringIO()) == 0 and not start3.started
    monkeypatch.setattr(plots, "plot_all", real_plot_all)
    assert sweep(_args(out, "comm.range_m=50"), start=start3, stream=io.StringIO()) == 0 and len(start3.started) == 6

    doc = json.loads((out / "sweep.json").read_text())
    assert doc["seeds"] == [0, 1, 2] and doc["frames"] == 2 and doc["grid"][0]["values"] == [0, 0.5]
    assert doc["methods"] == ["none", "attfuse", "cobevt"] and len(doc["rows"]) == 18
    st = next(s for s in doc["stats"] if s["metric"] == "iou_vehicle" and s["point"] == {"comm.drop.p": 0})
    assert st["resampled"] == "seeds" and st["methods"]["cobevt"]["seeds"] == 3
    diffs = {(x["a"], x["b"]): x for x in st["differences"]}
    assert set(diffs) == {("attfuse", "none"), ("cobevt", "none"), ("cobevt", "attfuse")}
    assert diffs[("cobevt", "none")]["mean"] == pytest.approx(0.2)  # paired: the seed effect cancels
    assert diffs[("cobevt", "none")]["lo"] == pytest.approx(0.2) and diffs[("cobevt", "none")]["excludes_zero"]
    md = (out / "sweep.md").read_text()
    assert "## comm.drop.p" in md and "| cobevt - none |" in md and "+0.200 [0.200, 0.200] **\\***" in md
    for m in ("iou_vehicle", "iou_vehicle_frame_mean", "ap50", "ap70"):
        assert (out / f"sweep_comm.drop.p_{m}.png").stat().st_size > 5000


class DegradingStarter(FakeStarter):
    """Runs that go through every frame; those in `degraded` lose cav1 at frame 1 (what the ego then says), or with
    `flagged` only have cav1 flagged by the misbehaviour check (issue 55)."""

    def __init__(self, degraded: set[tuple[str, int]], flagged: bool = False) -> None:
        super().__init__()
        self.degraded = degraded
        self.flagged = flagged

    def __call__(self, spec: plan_mod.RunSpec) -> FakeJob:
        job = super().__call__(spec)
        if (spec.point.texts[0], spec.seed) in self.degraded:
            if self.flagged:
                doc = _fake_metrics(spec) | {"status": "degraded: cav1 disagreed in 7 of 40 frames"}
            else:
                doc = _fake_metrics(spec) | {"status": "degraded: cav1 lost from frame 1", "lost_agents": {"cav1": 1}}
                doc["methods"]["cobevt"]["iou_vehicle"] = 0.0  # what a lost neighbour costs: not a configured run's
            spec.out.joinpath("metrics.json").write_text(json.dumps(doc))
        return job


def test_degraded_runs_are_rows_with_their_status_left_out_of_the_intervals_and_rerun_on_resume(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 45: a run that lost agents went through every frame: no failure (exit 0), its rows are in sweep.csv
    with its status, and the statistics leave it out unless --include-degraded; a resumed sweep runs it again."""
    import io

    from v2vsim.study import plots

    monkeypatch.setattr(runs_mod.time, "sleep", lambda s: None)
    monkeypatch.setattr(plots, "plot_all", lambda *a, **k: [])
    out = tmp_path / "sweep"
    log = io.StringIO()
    assert sweep(_args(out), start=DegradingStarter({("0", 1)}), stream=log) == 0
    text = log.getvalue()
    assert "run [comm.drop.p=0] seed 1 degraded: cav1 lost from frame 1; its rows are kept" in text
    assert "5 of 6 runs complete, 1 degraded (left out of the intervals), 0 failed" in text
    rows = _csv(out / "sweep.csv")
    assert list(rows[0])[:3 + len(CONTRACT_METRICS)] == ["comm.drop.p", "seed", "method", *CONTRACT_METRICS]
    assert list(rows[0])[-1] == "status" and len(rows) == 6 * 3
    assert [r["status"] for r in rows if (r["comm.drop.p"], r["seed"]) == ("0", "1")] == \
        ["degraded: cav1 lost from frame 1"] * 3
    assert {r["status"] for r in rows if (r["comm.drop.p"], r["seed"]) != ("0", "1")} == {"complete"}
    doc = json.loads((out / "sweep.json").read_text())
    assert doc["runs"]["complete"] == 5 and doc["runs"]["failed"] == [] and not doc["runs"]["include_degraded"]
    assert doc["runs"]["degraded"] == [{"point": "comm.drop.p=0", "seed": 1, "status": "degraded: cav1 lost from "
                                        "frame 1", "run": "runs/comm.drop.p=0/seed1"}]
    assert {r["status"] for r in doc["rows"] if r["seed"] == 1 and r["point"] == "comm.drop.p=0"} == {
        "degraded: cav1 lost from frame 1"}

    def cobevt(d: dict) -> dict:
        st = next(s for s in d["stats"] if s["metric"] == "iou_vehicle" and s["point"] == {"comm.drop.p": 0})
        return st["methods"]["cobevt"]

    assert cobevt(doc)["seeds"] == 2 and cobevt(doc)["mean"] == pytest.approx(0.61)  # seeds 0 and 2 only
    md = (out / "sweep.md").read_text()
    assert "1 degraded" in md and "- comm.drop.p=0 seed 1: degraded: cav1 lost from frame 1" in md
    assert "left out of the tables and plots below (--include-degraded counts them)" in md

    # --include-degraded: the same runs (reused) counted; a resume without it runs the degraded one again
    start = DegradingStarter({("0", 1)})
    assert sweep(_args(out), start=start, stream=io.StringIO()) == 0 and start.started == [("0", 1)]
    counted = tmp_path / "counted"
    assert sweep(SweepArgs(**{**_args(counted).__dict__, "include_degraded": True}),
                 start=DegradingStarter({("0", 1)}), stream=io.StringIO()) == 0
    doc = json.loads((counted / "sweep.json").read_text())
    assert doc["runs"]["include_degraded"] and cobevt(doc)["seeds"] == 3
    assert cobevt(doc)["mean"] == pytest.approx((0.6 + 0.0 + 0.62) / 3)
    assert "**counted** in the tables" in (counted / "sweep.md").read_text()


def test_a_run_degraded_only_by_a_flagged_sender_is_counted_and_said_to_be(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run whose only degradation is the misbehaviour check's flag went as configured: the statistics count it,
    and neither the terminal nor sweep.md may say it was left out."""
    import io

    from v2vsim.study import plots

    monkeypatch.setattr(runs_mod.time, "sleep", lambda s: None)
    monkeypatch.setattr(plots, "plot_all", lambda *a, **k: [])
    out = tmp_path / "sweep"
    log = io.StringIO()
    assert sweep(_args(out), start=DegradingStarter({("0", 1)}, flagged=True), stream=log) == 0
    text = log.getvalue()
    assert "5 of 6 runs complete, 1 with a sender flagged by the misbehaviour check (counted in the intervals), 0 " \
           "failed" in text and "left out of" not in text
    doc = json.loads((out / "sweep.json").read_text())
    st = next(s for s in doc["stats"] if s["metric"] == "iou_vehicle" and s["point"] == {"comm.drop.p": 0})
    assert st["methods"]["cobevt"]["seeds"] == 3
    md = (out / "sweep.md").read_text()
    assert "**Runs with a sender flagged**" in md and "- comm.drop.p=0 seed 1: degraded: cav1 disagreed" in md
    assert "left out of the tables" not in md


def test_two_keys_and_ctrl_c_keeps_what_finished(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import io

    monkeypatch.setattr(runs_mod.time, "sleep", lambda s: None)
    out = tmp_path / "sweep"
    args = _args(out, grid=("comm.drop.p=0,0.5", "comm.latency_ms.mean=0,100"), seeds="0-1")
    start = FakeStarter(interrupt_at=5)
    log = io.StringIO()
    assert sweep(args, start=start, stream=log) == 130
    assert "interrupted" in log.getvalue() and len(start.started) == 5
    doc = json.loads((out / "sweep.json").read_text())
    assert doc["interrupted"] and doc["runs"]["complete"] == 5 and len(_csv(out / "sweep.csv")) == 5 * 3
    md = (out / "sweep.md").read_text()
    assert "## comm.latency_ms.mean" in md and "at comm.drop.p=0.5" in md and "at comm.latency_ms.mean=100" in md
    assert (out / "sweep_comm.latency_ms.mean_ap70.png").is_file()
    from v2vsim.study import plots

    monkeypatch.setattr(plots, "plot_all", lambda *a, **k: [])
    start = FakeStarter()
    assert sweep(args, start=start, stream=io.StringIO()) == 0 and len(start.started) == 3  # 8 runs, 5 kept


class SlowStarter(FakeStarter):
    """Runs that take a few polls each; records how many run at once."""

    def __init__(self) -> None:
        super().__init__()
        self.live: list[FakeJob] = []
        self.most = 0

    def __call__(self, spec: plan_mod.RunSpec) -> FakeJob:
        job = super().__call__(spec)
        polls = iter([None, None, 0])
        job.poll = lambda: self._poll(job, polls)  # type: ignore[method-assign]
        self.live.append(job)
        self.most = max(self.most, len(self.live))
        return job

    def _poll(self, job: FakeJob, polls: object) -> int | None:
        code = next(polls, 0)  # type: ignore[call-overload]
        if code is not None and job in self.live:
            self.live.remove(job)
        return code


def test_jobs_caps_the_runs_at_a_time_and_no_grid_is_one_point(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import io

    from v2vsim.study import plots

    monkeypatch.setattr(runs_mod.time, "sleep", lambda s: None)
    monkeypatch.setattr(plots, "plot_all", lambda *a, **k: [])
    start = SlowStarter()
    args = SweepArgs(SCENARIO, ("comm.drop.p=0,0.5,1",), "0-3", tmp_path / "a", frames=2, jobs=3, replay=False)
    assert sweep(args, start=start, stream=io.StringIO()) == 0
    assert len(start.started) == 12 and start.most == 3
    start = SlowStarter()
    args = SweepArgs(SCENARIO, (), "0-1", tmp_path / "b", frames=2, overrides=("comm.drop.p=0.5",), replay=False)
    assert sweep(args, start=start, stream=io.StringIO()) == 0 and start.most == 1
    assert (tmp_path / "b" / "runs" / "base" / "seed1" / "metrics.json").is_file()
    assert list(_csv(tmp_path / "b" / "sweep.csv")[0])[:2] == ["seed", "method"]
    md = (tmp_path / "b" / "sweep.md").read_text()
    assert "## Results" in md and "| (no grid) |" in md
    assert "lane IoU" not in md  # null in every run: no table


# ---- record once, replay the rest ------------------------------------------------------------------------


def test_points_that_differ_only_in_receiver_side_keys_replay_the_first_ones_recording(tmp_path: Path) -> None:
    d = prepare(SweepArgs(SCENARIO, ("cavs.count=2,3", "comm.drop.p=0,0.5", "comm.latency_ms.mean=0,100"), "0-1",
                          tmp_path, frames=2))
    by = {(s.point.texts, s.seed): s for s in d.specs}
    for count in ("2", "3"):  # sender-side: each count is simulated and recorded at each seed
        for seed in (0, 1):
            rec = by[((count, "0", "0"), seed)]
            assert rec.records and not rec.replayed and "output.record_messages=true" in rec.request["overrides"]
            assert rec.argv(d.scenario)[:3] == ["-m", "v2vsim.cli", "run"]
            for texts in ((count, "0", "100"), (count, "0.5", "0"), (count, "0.5", "100")):
                s = by[(texts, seed)]
                assert s.recording == rec.out and not s.records and s.request["replay_of"] == str(rec.out)
                argv = s.argv(d.scenario)
                assert argv[:4] == ["-m", "v2vsim.cli", "evaluate", str(rec.out)]
                assert f"seed={seed}" in argv and "comm.drop.p=" + texts[1] in argv and argv[-2:] == ["--frames", "2"]
                assert "output.record_messages=true" not in s.request["overrides"]
    assert sum(s.replayed for s in d.specs) == 12
    # the methods and the output keys are not replayed across: a recording holds its own methods' kinds
    d = prepare(_args(tmp_path, grid=("perception.methods=[none,cobevt],[none,late]",), seeds="0", replay=True))
    assert not any(s.replayed or s.records for s in d.specs)
    d = prepare(_args(tmp_path, grid=("duration_s=1,2",), seeds="0", replay=True))  # another number of frames
    assert not any(s.replayed or s.records for s in d.specs)
    # a realtime point has nothing to record: on a swept clock only the lockstep points replay
    d = prepare(_args(tmp_path, grid=("transport.clock=lockstep,realtime", "comm.drop.p=0,0.5"), seeds="0",
                      replay=True))
    assert [(s.point.texts, s.records, s.replayed) for s in d.specs] == [
        (("lockstep", "0"), True, False), (("lockstep", "0.5"), False, True),
        (("realtime", "0"), False, False), (("realtime", "0.5"), False, False)]
    # a closed-loop point (issue 46) runs live: its ego drove on what it perceived, so even a channel key changes
    # what the CAVs sensed; the open-loop points of the same sweep still replay
    d = prepare(_args(tmp_path, grid=("control.method=oracle,none", "comm.latency_ms.mean=0,100"), seeds="0",
                      replay=True))
    assert not any(s.replayed or s.records for s in d.specs) and len(d.specs) == 4
    # the dask engine and the realtime clock simulate every run, saying why
    assert prepare(_args(tmp_path, "transport.clock=realtime", replay=True)).no_replay.startswith("transport.clock")
    assert prepare(_args(tmp_path)).no_replay == "--no-replay"


def test_a_recordings_replays_run_in_as_few_processes_as_fill_the_replay_slots(tmp_path: Path) -> None:
    """One seed, --jobs 1 (two replay slots): the 11 replays of the README grid in two processes of neighbouring
    points; five seeds: one process per seed; --jobs 3 with one seed: six."""
    assert plan_mod.batches_per_recording(recordings=1, replays=11, jobs=1) == 2
    assert plan_mod.batches_per_recording(recordings=5, replays=11, jobs=1) == 1
    assert plan_mod.batches_per_recording(recordings=1, replays=11, jobs=3) == 6
    assert plan_mod.batches_per_recording(recordings=1, replays=1, jobs=4) == 1
    grid = ("comm.latency_ms.mean=0,100,200,300", "comm.drop.p=0,0.1,0.3")
    d = prepare(SweepArgs(SCENARIO, grid, "10", tmp_path / "one", frames=2, jobs=1))
    replays = [s for s in d.specs if s.replayed]
    # contiguous in grid order, cut between two latencies (0 and 100 | 200 and 300), not inside one
    assert len(replays) == 11 and [s.batch for s in replays] == [0] * 5 + [1] * 6
    assert plan_mod.cut_points([(lat, p) for lat in "abcd" for p in "xyz"][1:], 3) == [5, 8]
    assert plan_mod.cut_points([("a",)] * 5, 2) == [2]  # one value: equal halves
    d = prepare(SweepArgs(SCENARIO, grid, "10-14", tmp_path / "five", frames=2, jobs=1))
    batches = {}
    for s in d.specs:
        if s.replayed:
            batches.setdefault((s.recording, s.batch), set()).add(s.seed)
    assert len(batches) == 5 and all(len(seeds) == 1 for seeds in batches.values())
    lead = next(s for s in d.specs if s.replayed)
    rest = tuple(s for s in d.specs if s.replayed and s.batch == lead.batch and s is not lead)
    together = dataclasses.replace(lead, together=rest)
    argv = together.argv(d.scenario)
    assert argv[:5] == ["-m", "v2vsim.cli", "evaluate", str(lead.recording), "--plan"]
    assert argv[-2:] == ["--frames", "2"]
    assert [x["out"] for x in together.plan_doc()] == [str(s.out) for s in (lead, *rest)]
    assert together.plan_doc()[1]["overrides"] == rest[0].request["overrides"]


def test_a_replay_waits_for_its_recording_and_fails_with_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import io

    from v2vsim.study import plots

    monkeypatch.setattr(runs_mod.time, "sleep", lambda s: None)
    monkeypatch.setattr(plots, "plot_all", lambda *a, **k: [])
    out = tmp_path / "sweep"
    start = SlowStarter()
    start.fail = {("0", 1)}  # seed 1's recording run fails
    log = io.StringIO()
    assert sweep(SweepArgs(SCENARIO, ("comm.drop.p=0,0.5,1",), "0-2", out, frames=2, jobs=3), start=start,
                 stream=log) == 1
    text = log.getvalue()
    # --jobs 3: six replay slots, so each replay in its own process
    assert "3 runs simulated, 6 replayed (6 v2vsim evaluate process(es)) from the recordings of point(s) " \
        "comm.drop.p=0" in text
    # every replay started after its seed's recording run had finished; seed 1's were never started
    order = start.started
    assert sorted(order) == [("0", 0), ("0", 1), ("0", 2), ("0.5", 0), ("0.5", 2), ("1", 0), ("1", 2)]
    for p in ("0.5", "1"):
        for seed in (0, 2):
            assert order.index((p, seed)) > order.index(("0", seed))
    assert f"[comm.drop.p=0.5] seed 1 failed (not replayed: the run it replays ({out}/runs/comm.drop.p=0/seed1)" in text
    doc = json.loads((out / "sweep.json").read_text())
    assert doc["runs"]["simulated"] == 3 and doc["runs"]["replayed"] == 6 and len(doc["runs"]["failed"]) == 3
    assert doc["runs"]["replayed_points"] == ["comm.drop.p=0.5", "comm.drop.p=1"]
    assert "3 runs simulated, 6 replayed with `v2vsim evaluate`" in (out / "sweep.md").read_text()

    # resumed: the recording run again, then its replays; a recording run whose recording is gone reruns too
    (out / "runs" / "comm.drop.p=0" / "seed2" / "messages" / "header.json").unlink()
    start = FakeStarter()
    assert sweep(SweepArgs(SCENARIO, ("comm.drop.p=0,0.5,1",), "0-2", out, frames=2), start=start,
                 stream=io.StringIO()) == 0
    assert start.started == [("0", 1), ("0", 2), ("0.5", 1), ("1", 1)]


# ---- statistics ------------------------------------------------------------------------------------------


def _ar1(rng: np.random.Generator, n: int, sd: float, phi: float) -> np.ndarray:
    x = np.empty(n)
    x[0] = rng.normal(0, sd)
    for t in range(1, n):
        x[t] = phi * x[t - 1] + rng.normal(0, sd * np.sqrt(1 - phi**2))
    return x


@pytest.mark.parametrize("frames", [20, 1])  # seeds and frames; seeds only (whole-run metrics)
def test_bootstrap_intervals_cover_the_true_difference_at_about_the_stated_rate(frames: int) -> None:
    """200 synthetic paired studies: 10 seeds with a per-seed effect, correlated frames within a seed."""
    rng = np.random.default_rng(2024)
    true, hits, studies = 0.05, 0, 200
    for i in range(studies):
        a, b = [], []
        for _ in range(10):
            seed_effect = rng.normal(0, 0.04)
            base = rng.uniform(0.3, 0.6) + _ar1(rng, frames, 0.08, 0.5)  # shared by both methods (paired)
            b.append(dict(enumerate(base)))
            a.append(dict(enumerate(base + true + seed_effect + _ar1(rng, frames, 0.1, 0.5))))
        iv = interval(paired_clusters(a, b), b=500, label=f"study{i}")
        assert iv is not None and iv.seeds == 10 and iv.frames == 10 * frames
        hits += iv.lo <= true <= iv.hi
    assert 0.9 <= hits / studies <= 0.99, hits / studies


def test_interval_edge_cases() -> None:
    assert interval([]) is None and interval([[np.nan]]) is None
    one = interval([[0.3]])
    assert one is not None and one.mean == 0.3 and one.lo is None and one.excludes_zero is None
    iv = interval([[0.1, 0.2, 0.3], [0.5]], b=300, label="x")
    assert iv is not None and iv.mean == pytest.approx((0.2 + 0.5) / 2)  # every seed weighs the same
    assert iv == interval([[0.1, 0.2, 0.3], [0.5]], b=300, label="x")  # a fixed RNG: reproducible
    assert paired_clusters([{0: 0.5, 1: 0.6, 3: 0.1}, {}], [{1: 0.4, 3: 0.2, 4: 0.9}, {0: 1.0}])[0].tolist() == \
        pytest.approx([0.2, -0.1])  # only frames both methods scored


def test_vehicle_iou_is_resampled_over_frames_when_every_run_has_them(tmp_path: Path) -> None:
    from v2vsim.study.grid import points
    from v2vsim.study.rows import Row
    from v2vsim.study.summary import point_stats

    (pt,) = points(parse_axes(["comm.drop.p=0"]))
    rows = []
    for seed in range(4):
        for m, shift in (("none", 0.0), ("cobevt", 0.1)):
            per_frame = {f: 0.4 + shift + 0.05 * np.sin(f + seed) for f in range(6) if (m, f) != ("none", 5)}
            metrics = {"iou_vehicle_frame_mean": float(np.mean(list(per_frame.values()))), "ap70": 0.5 + shift}
            rows.append(Row(pt, seed, m, metrics, tmp_path, per_frame))
    (fm,) = point_stats(rows, [pt], "iou_vehicle_frame_mean", 300, 0)
    assert fm.level == "seeds and frames" and fm.methods["cobevt"].frames == 24
    assert fm.differences[("cobevt", "none")].frames == 20  # paired on the frames both scored
    assert fm.differences[("cobevt", "none")].mean == pytest.approx(0.1)
    (ap,) = point_stats(rows, [pt], "ap70", 300, 0)
    assert ap.level == "seeds" and ap.methods["none"].frames == 4
    assert point_stats(rows, [pt], "iou_lane", 300, 0) == []  # no value anywhere
    rows[0] = Row(pt, 0, "none", rows[0].metrics, tmp_path, None)  # one run without a recording
    assert point_stats(rows, [pt], "iou_vehicle_frame_mean", 300, 0)[0].level == "seeds"


def test_per_frame_values_are_keyed_by_the_runs_frame_indices_and_run_intervals_are_no_columns(
        tmp_path: Path) -> None:
    from v2vsim.study.grid import points
    from v2vsim.study.rows import collect, metric_columns

    (pt,) = points(parse_axes(["comm.drop.p=0"]))
    spec = plan_mod.RunSpec(pt, 0, tmp_path, (), {})
    late = {"iou_vehicle": 0.5, "iou_vehicle_counts": [[1, 2], [3, 4], [0, 0]], "iou_vehicle_frames": [0, 2, 3],
            "vs_none": {"iou_vehicle": {"diff": 0.1, "low": 0.0, "high": 0.2, "excludes_zero": False}}}
    old = {"iou_vehicle": 0.4, "iou_vehicle_counts": [[1, 4], [2, 4]]}  # written before the frame indices
    (tmp_path / "metrics.json").write_text(json.dumps({"methods": {"late": late, "none": old}}))
    rows = collect([runs_mod.RunResult(spec, ok=True)])
    assert rows[0].per_frame == {0: 0.5, 2: 0.75}  # frame 1 had no input for late; frame 3 no union
    assert rows[1].per_frame == {0: 0.25, 1: 0.5}
    assert metric_columns(rows) == CONTRACT_METRICS  # no vs_none, frames or counts column in sweep.csv


def test_per_frame_values_come_from_the_recording(tmp_path: Path) -> None:
    import rerun as rr

    from v2vsim.study.rows import per_frame_vehicle_iou

    rrd = tmp_path / "recording.rrd"
    rec = rr.RecordingStream("v2vsim-test")
    rec.save(str(rrd))
    for f in range(4):
        rec.set_time("frame", sequence=f)
        rec.log("metrics/iou_vehicle/cobevt", rr.Scalars(0.5 + 0.1 * f))
        if f != 2:  # a frame without vehicle cells for this method is not logged
            rec.log("metrics/iou_vehicle/none", rr.Scalars(0.25))
    rec.flush()
    rec.disconnect()
    got = per_frame_vehicle_iou(rrd)
    assert got["cobevt"] == pytest.approx({0: 0.5, 1: 0.6, 2: 0.7, 3: 0.8}) and got["none"] == {0: 0.25, 1: 0.25,
                                                                                                3: 0.25}
    (tmp_path / "broken.rrd").write_bytes(b"not a recording")
    assert per_frame_vehicle_iou(tmp_path / "broken.rrd") == {}


# ---- the real thing --------------------------------------------------------------------------------------


def test_real_sweep_writes_the_contract_csv_and_plots_and_replays_bit_for_bit(tmp_path: Path) -> None:
    import subprocess

    out = tmp_path / "sweep"
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "sweep", str(SCENARIO), "--grid",
                        "comm.drop.p=0,0.25,0.5,0.75", "--seeds", "0-0", "--frames", "3", "--set", "cavs.count=2",
                        "--methods", "none,cobevt", "--bootstrap", "200", "--out", str(out)], capture_output=True,
                       text=True, cwd=REPO, timeout=240)
    took = time.monotonic() - t0
    assert r.returncode == 0, r.stderr
    print(f"real sweep: {took:.1f} s")
    assert "v2vsim sweep: 4/4 runs, 0 running" in r.stderr
    rows = _csv(out / "sweep.csv")
    assert list(rows[0])[:3 + len(CONTRACT_METRICS)] == ["comm.drop.p", "seed", "method", *CONTRACT_METRICS]
    assert [(x["comm.drop.p"], x["seed"], x["method"]) for x in rows] == [
        (p, "0", m) for p in ("0", "0.25", "0.5", "0.75") for m in ("none", "cobevt")]
    for x in rows:
        assert 0 <= float(x["iou_vehicle"]) <= 1 and float(x["fusion_ms"]) > 0
    run = out / "runs" / "comm.drop.p=0.5" / "seed0"
    m = json.loads((run / "metrics.json").read_text())
    assert m["status"] == "complete" and m["frames"] == 3 and m["cavs"] == 2
    # the run's own intervals against none, and the frame indices the methods are paired on
    assert "vs_none" in m["methods"]["cobevt"] and "vs_none" not in m["methods"]["none"]
    assert m["methods"]["cobevt"]["iou_vehicle_frames"] == m["methods"]["none"]["iou_vehicle_frames"] == [0, 1, 2]
    assert "vs_none" not in rows[0] and "iou_vehicle_frames" not in rows[0]
    assert not (run / "recording.rrd").exists()  # output.rerun=false by default in a sweep
    for name in ("sweep.json", "sweep.md", "sweep_comm.drop.p_iou_vehicle.png", "sweep_comm.drop.p_ap50.png",
                 "sweep_comm.drop.p_ap70.png"):
        assert (out / name).stat().st_size > 0, name

    # drop.p=0.25, 0.5 and 0.75 were replayed from drop.p=0's recording, in two processes for the two replay
    # slots: 0.25 and 0.5 in one (one pass, shared work), 0.75 in the other
    assert "1 runs simulated, 3 replayed (2 v2vsim evaluate process(es)) from the recordings of point(s) " \
        "comm.drop.p=0" in r.stderr
    assert (out / "runs" / "comm.drop.p=0" / "seed0" / "messages" / "header.json").is_file()
    first = out / "runs" / "comm.drop.p=0.25" / "seed0"
    assert "replayed in one process with comm.drop.p=0.25" in (run / "sweep-run.log").read_text()
    log = (first / "sweep-run.log").read_text()
    assert "2 points replayed in one pass" in log and log.count("frame 3/3") == 2, log
    assert json.loads((first / "replay_plan.json").read_text())[1]["out"] == str(run)
    assert "frame 3/3" in (out / "runs" / "comm.drop.p=0.75" / "seed0" / "sweep-run.log").read_text()
    assert not (run / "messages").exists()
    recorded = out / "runs" / "comm.drop.p=0" / "seed0"
    assert json.loads((run / "sweep_run.json").read_text())["replay_of"] == str(recorded)
    live = tmp_path / "live"
    r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "sweep", str(SCENARIO), "--grid", "comm.drop.p=0.5",
                        "--seeds", "0-0", "--frames", "3", "--set", "cavs.count=2", "--methods", "none,cobevt",
                        "--bootstrap", "200", "--no-replay", "--out", str(live)], capture_output=True, text=True,
                       cwd=REPO, timeout=240)
    assert r.returncode == 0, r.stderr
    assert "every run is simulated (--no-replay)" in r.stderr
    timing = {"fusion_ms"}
    # simulated instead, drop.p=0.5 scores the same, bit for bit
    assert [{k: v for k, v in x.items() if k not in timing} for x in _csv(live / "sweep.csv")] == [
        {k: v for k, v in x.items() if k not in timing} for x in rows[4:6]]


def test_dask_engine_options_are_checked(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    from v2vsim.study import cluster

    base = ["sweep", str(SCENARIO), "--seeds", "0", "--out", str(tmp_path / "s")]
    assert main([*base, "--engine", "dask"]) == 2
    assert "--engine dask needs --scheduler" in capsys.readouterr().err
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT_S", 1.0)  # Dask retries a refused port until the timeout (10 s)
    assert main([*base, "--engine", "dask", "--scheduler", "tcp://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert "--scheduler tcp://127.0.0.1:9: no Dask scheduler answered" in err and "\n" not in err.strip(), err


def test_retrained_weights_rerun_every_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import io

    from v2vsim.study import plots

    monkeypatch.setattr(runs_mod.time, "sleep", lambda s: None)
    monkeypatch.setattr(plots, "plot_all", lambda *a, **k: [])
    out = tmp_path / "sweep"
    assert sweep(_args(out), start=FakeStarter(), stream=io.StringIO()) == 0
    again = FakeStarter()
    assert sweep(_args(out), start=again, stream=io.StringIO()) == 0 and not again.started
    assert json.loads(next(out.glob("runs/*/seed0/sweep_run.json")).read_text())["weights"]  # the manifest's sha256
    monkeypatch.setattr(plan_mod, "weights_fingerprint", lambda *a: "another zoo")
    again = FakeStarter()
    assert sweep(_args(out), start=again, stream=io.StringIO()) == 0 and len(again.started) == 6


def test_a_key_added_since_a_run_counts_as_its_default() -> None:
    """A finished run recorded before comm.share (or any key) existed is the same run while the key is at its
    default; a non-default value, a changed value or a key that went away is another run."""
    from v2vsim.study.plan import effective_config, same_config

    new = effective_config(Path(SCENARIO), [])
    old = json.loads(json.dumps(new))
    del old["comm"]["share"], old["comm"]["medium"]
    assert same_config(old, new)
    assert not same_config(old, effective_config(Path(SCENARIO), ["comm.share.fraction=0.5"]))
    assert not same_config(old, effective_config(Path(SCENARIO), ["comm.medium=shared"]))
    assert not same_config(old, effective_config(Path(SCENARIO), ["comm.drop.p=0.1"]))
    gone = json.loads(json.dumps(new))
    gone["comm"]["retired_key"] = 1
    assert not same_config(gone, new)
