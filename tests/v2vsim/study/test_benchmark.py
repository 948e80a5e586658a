"""`v2vsim benchmark`: the catalogue (shipped, thinned by a profile, malformed ones refused in one line), the
leaderboard on hand-made runs (scores, efficiency, paired intervals, the power estimate), interruption and resume
with fake runs, and `control.perceive: driving`."""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest

from v2vsim.cli import main
from v2vsim.config import ConfigError, load_scenario
from v2vsim.study import runs as runs_mod
from v2vsim.study.benchmark import DRIVING_ONLY, BenchmarkArgs, benchmark, family_sweeps
from v2vsim.study.catalogue import load_catalogue
from v2vsim.study.leaderboard import Episode, auc, board, config_table, episodes_of, needed_episodes
from v2vsim.study.plan import RunSpec

REPO = Path(__file__).resolve().parents[3]
TJ = REPO / "scenarios" / "t_junction_occluded.yaml"


def _catalogue(tmp_path: Path, **changes: object) -> Path:
    doc = {"methods": ["oracle", "none", "cobevt"], "seeds": {"tuning": "100-104", "heldout": "0-4"},
           "profiles": {"quick": {"seeds": 3, "levels": [2], "methods": ["oracle", "none", "cobevt"]}},
           "families": [{"name": "pullout", "scenario": str(TJ), "pre_crash": "crossing", "occlusion": "buildings",
                         "grid": {"traffic.hidden_foe.arrival_offset_s": [[0, 0], [1, 1], [2, 2]]}}]}
    for k, v in changes.items():
        doc[k] = v
    path = tmp_path / "catalogue.yaml"
    path.write_text(json.dumps(doc))  # JSON is YAML
    return path


def test_the_shipped_catalogue_loads_and_a_profile_thins_each_grid_axis_evenly() -> None:
    cat = load_catalogue()
    assert cat.methods[:2] == ("oracle", "none") and len(cat.families) >= 1
    assert not set(cat.seeds["tuning"]) & set(cat.seeds["heldout"])
    for f in cat.families:
        assert load_scenario(f.scenario).control is not None, f.name  # `v2vsim run NAME` drives
        for a in f.grid:
            for v in a.texts:  # every grid value loads with the family's scenario
                load_scenario(f.scenario, [f"{a.key}={v}"])
    f = cat.families[0]
    from v2vsim.study.grid import Axis

    a = Axis("k", ("0", "1", "2", "3", "4"), (0, 1, 2, 3, 4))
    fam = type(f)("x", f.scenario, "", "", (a, a))
    assert [x.texts for x in fam.axes((1, 2))] == [("2",), ("0", "4")]
    assert [x.texts for x in fam.axes((3,))] == [("0", "2", "4"), ("2",)]  # an axis the profile omits: 1 value
    assert fam.axes((9, 5))[0].texts == a.texts


@pytest.mark.parametrize(("change", "expect"), [
    ({"methods": ["none", "oracle"]}, "methods: must start with oracle, none"),
    ({"methods": ["oracle", "none", "nope"]}, "methods[2]: 'nope' is no method"),
    ({"seeds": {"tuning": "0-5", "heldout": "4-9"}}, "seeds: tuning and heldout seeds overlap"),
    ({"seeds": {"tuning": "0-5"}}, "seeds.heldout: missing"),
    ({"seeds": {"tuning": "x", "heldout": "4-9"}}, "seeds.tuning: --seeds 'x'"),
    ({"profiles": {"quick": {"seeds": 0, "levels": [1]}}}, "profiles.quick.seeds: expected an integer >= 1"),
    ({"profiles": {"quick": {"seeds": 1, "levels": [1], "methods": ["oracle", "late"]}}},
     "profiles.quick.methods: 'late' is not among the catalogue's methods"),
    ({"colour": 1}, "colour: unknown key"),
    ({"families": [{"name": "a", "scenario": "nowhere.yaml", "grid": {"seed": [1]}}]},
     "families[0].scenario: no such file"),
    ({"families": [{"name": "a", "scenario": str(TJ), "grid": {"seed": [1, 2]}}]},
     "families[0].grid.seed: --grid seed=1,2: seed cannot be swept here"),
    ({"families": [{"name": "a", "scenario": str(TJ), "grid": {"comm.range_m": 5}}]},
     "families[0].grid.comm.range_m: expected a non-empty list"),
    ({"families": [{"name": "a", "scenario": str(TJ), "grid": {"comm.range_m": [5]}, "sees": "cav1"}]},
     "families[0].sees: expected a list of CAV ids"),
])
def test_a_malformed_catalogue_is_one_line_naming_the_file_and_key(tmp_path: Path, change: dict, expect: str) -> None:
    path = _catalogue(tmp_path, **change)
    with pytest.raises(ConfigError, match="catalogue.yaml: ") as e:
        load_catalogue(path)
    assert expect in str(e.value) and "\n" not in str(e.value)


def test_control_perceive_driving_computes_only_the_method_it_drives_on() -> None:
    sc = load_scenario(TJ, ["control.method=attfuse", DRIVING_ONLY])  # attfuse is not in the file's methods
    assert sc.perception.methods == ("attfuse",)
    assert load_scenario(TJ, ["control.method=oracle", DRIVING_ONLY]).perception.methods == ("none",)
    assert load_scenario(TJ).perception.methods == ("none", "late", "cobevt", "v2vnet")  # all: as before
    with pytest.raises(ConfigError, match="control.method: 'attfuse' is not among perception.methods"):
        load_scenario(TJ, ["control.method=attfuse"])
    with pytest.raises(ConfigError, match="control.method: 'x' is no fusion method; allowed: oracle, none"):
        load_scenario(TJ, ["control.method=x", DRIVING_ONLY])


# ---- the leaderboard on hand-made runs -----------------------------------------------------------------------

def _total(method: str, offset: int, seed: int) -> dict:
    """oracle: always succeeds at 10 s; none: collides at offset 0 and on odd seeds (score 0.6 x completion 0.5),
    else succeeds at 8 s; cobevt: collides at offset 0 on seed 0 only, else succeeds at 12.5 s."""
    collides = {"oracle": False, "none": offset == 0 or seed % 2 == 1, "cobevt": offset == 0 and seed == 0}[method]
    finished = None if collides else {"oracle": 10.0, "none": 8.0, "cobevt": 12.5}[method]
    return {"collisions": int(collides), "driving_score": 0.3 if collides else 1.0, "success": not collides,
            "route_completion": 0.5 if collides else 1.0, "finished_at_s": finished,
            "infractions": {"collision_vehicle": int(collides), "timeout": 0}}


def _metrics(spec: RunSpec) -> dict:
    over = dict(o.split("=", 1) for o in spec.request["overrides"])
    method, offset = over["control.method"], int(json.loads(over["traffic.hidden_foe.arrival_offset_s"])[0])
    row = "none" if method == "oracle" else method
    return {"status": "complete", "frames": 5, "methods": {row: {"iou_vehicle": 0.5 if row == "cobevt" else 0.2}},
            "driving": {"method": method, "total": _total(method, offset, spec.seed)}}


class FakeJob:
    def __init__(self, spec: RunSpec) -> None:
        (spec.out / runs_mod.LOG).write_text("v2vsim: done\n")
        spec.out.joinpath("metrics.json").write_text(json.dumps(_metrics(spec)))

    def poll(self) -> int | None:
        return 0

    def interrupt(self) -> None:
        pass

    def kill(self) -> None:
        pass


class FakeStarter:
    def __init__(self, interrupt_at: int | None = None) -> None:
        self.started: list[tuple[str, int]] = []
        self.interrupt_at = interrupt_at

    def __call__(self, spec: RunSpec) -> FakeJob:
        if self.interrupt_at is not None and len(self.started) == self.interrupt_at:
            raise KeyboardInterrupt
        self.started.append((spec.point.pid, spec.seed))
        assert DRIVING_ONLY in spec.request["overrides"]  # every run pays for the method it drives on only
        return FakeJob(spec)


def test_fake_benchmark_resumes_after_ctrl_c_and_writes_the_leaderboard(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(runs_mod.time, "sleep", lambda s: None)
    out = tmp_path / "bench"
    args = BenchmarkArgs(out=out, catalogue=_catalogue(tmp_path), bootstrap=300)
    [(name, s)] = family_sweeps(args, load_catalogue(args.catalogue))
    assert name == "pullout" and s.seeds == "0-2" and s.grid == (
        "control.method=oracle,none,cobevt", "traffic.hidden_foe.arrival_offset_s=[0, 0],[2, 2]")
    log = io.StringIO()
    first = FakeStarter(interrupt_at=7)
    assert benchmark(args, start=first, stream=log) == 130
    assert "run the same command again to resume" in log.getvalue() and not (out / "leaderboard.md").exists()
    again = FakeStarter()
    log = io.StringIO()
    assert benchmark(args, start=again, stream=log) == 0
    assert len(first.started) == 7 and len(again.started) == 18 - 7  # 3 methods x 2 configs x 3 seeds
    assert not set(first.started) & set(again.started)
    assert "7 reused" in log.getvalue()

    doc = json.loads((out / "leaderboard.json").read_text())
    overall = next(b for b in doc["boards"] if b["scope"] == "overall")
    assert overall["episodes"] == 6
    m = overall["methods"]
    # none collides in 4 of 6 episodes (offset 0: 3, offset 2: seed 1); cobevt in 1
    assert m["oracle"]["driving_score"]["mean"] == 1.0 and m["oracle"]["efficiency"]["mean"] == 1.0
    assert m["none"]["collision"]["mean"] == pytest.approx(4 / 6)
    assert m["none"]["driving_score"]["mean"] == pytest.approx((4 * 0.3 + 2) / 6)
    assert m["cobevt"]["success"]["mean"] == pytest.approx(5 / 6)
    assert m["cobevt"]["efficiency"]["mean"] == pytest.approx(0.8)  # 10 / 12.5 on the 5 it finished
    assert m["none"]["efficiency"]["mean"] == pytest.approx(1.25) and m["none"]["efficiency"]["seeds"] == 2
    assert m["oracle"]["iou_vehicle"] is None and m["cobevt"]["iou_vehicle"]["mean"] == 0.5
    d = overall["versus_none"]["cobevt"]["collision"]
    assert d["mean"] == pytest.approx(-0.5) and d["n"] == 6 and d["lo"] < -0.5 < d["hi"] <= 0.0
    pair = next(p for p in overall["pairs"] if (p["a"], p["b"], p["measure"]) == ("oracle", "cobevt",
                                                                                 "driving_score"))
    assert pair["mean"] == pytest.approx(0.7 / 6, abs=1e-6) and not pair["excludes_zero"]
    assert pair["needed_episodes"] == needed_episodes([0.7, 0, 0, 0, 0, 0]) > 6
    md = (out / "leaderboard.md").read_text()
    assert "## Overall (6 episodes)" in md and "## Family pullout (6 episodes)" in md
    rank = [ln.split("|")[1].strip() for ln in md.split("## Overall")[1].split("###")[0].splitlines()
            if ln.startswith("| ") and not ln.startswith("| method")]
    assert rank == ["oracle", "cobevt", "none"]
    assert "| cobevt | none | 6 |" in md
    # the calibration's view: per configuration, success / collision rate of each method over the seeds
    assert "| arrival_offset_s=[0, 0] | 3 | 1.00 / 0.00 | 0.00 / 1.00 | 0.67 / 0.33 |" in md
    assert "| arrival_offset_s=[2, 2] | 3 | 1.00 / 0.00 | 0.67 / 0.33 | 1.00 / 0.00 |" in md
    csv_head = (out / "leaderboard.csv").read_text().splitlines()[0]
    assert csv_head.startswith("scope,method,episodes,driving_score,driving_score_lo,driving_score_hi,")
    for png in ("leaderboard_score.png", "leaderboard_families.png"):
        assert (out / png).stat().st_size > 5000
    assert (out / "families" / "pullout" / "sweep.md").is_file()


def test_the_configuration_table_keeps_the_grids_order() -> None:
    # episodes as episodes_of reads them: the sweep's rows, in the grid's order (not the strings' order: 11 < 8)
    run = {"none": {"success": 1.0, "collision": 0.0}}
    eps = {Episode("f", f"arrival_offset_s=[{o}, {o}], speed_mps={v}", 0): run
           for o in ("-0.5", "0", "1") for v in ("8", "11", "14")}
    rows = [ln.split("|")[1].strip() for ln in config_table(eps, ["none"])[2:]]
    assert rows[:4] == ["arrival_offset_s=[-0.5, -0.5], speed_mps=8", "arrival_offset_s=[-0.5, -0.5], speed_mps=11",
                        "arrival_offset_s=[-0.5, -0.5], speed_mps=14", "arrival_offset_s=[0, 0], speed_mps=8"]
    assert rows[-1] == "arrival_offset_s=[1, 1], speed_mps=14"


def test_episodes_pair_methods_by_configuration_and_seed_and_skip_incomplete_runs() -> None:
    rows = [{"control.method": m, "traffic.hidden_foe.arrival_offset_s": [1, 1], "seed": s, "method": m,
             "status": "complete" if (m, s) != ("none", 1) else "degraded: cav1 lost",
             "driving_method": m, "driving_driving_score": 1.0, "driving_success": 1, "driving_collisions": 0,
             "driving_route_completion": 1.0, "driving_finished_at_s": 9.0, "iou_vehicle": 0.3}
            for m in ("none", "cobevt") for s in (0, 1)]
    doc = {"grid": [{"key": "control.method"}, {"key": "traffic.hidden_foe.arrival_offset_s"}], "rows": rows}
    eps = episodes_of("f", doc)
    assert set(eps) == {Episode("f", "arrival_offset_s=[1, 1]", 0), Episode("f", "arrival_offset_s=[1, 1]", 1)}
    assert set(eps[Episode("f", "arrival_offset_s=[1, 1]", 1)]) == {"cobevt"}
    b = board("f", eps, ["oracle", "none", "cobevt"], boot=200)
    assert "oracle" not in b.alone and b.versus_none["cobevt"]["driving_score"].n == 1


def test_needed_episodes_is_the_paired_normal_power_formula() -> None:
    assert needed_episodes([1.0]) is None and needed_episodes([0.0, 0.0]) is None
    # mean 0.1, sample sd 0.2 (two values 0.1 -+ 0.2 / sqrt 2): ((1.95996 + 0.84162) x 0.2 / 0.1)^2 = 31.4 -> 32
    diffs = [0.1 - 0.2 / 2 ** 0.5, 0.1 + 0.2 / 2 ** 0.5]
    assert needed_episodes(diffs) == 32
    assert needed_episodes([-x for x in diffs]) == 32


def test_benchmark_options_are_checked_before_anything_is_written(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "b"
    assert main(["benchmark", "--profile", "nope", "--out", str(out)]) == 2
    assert "--profile nope: allowed: quick, leaderboard, full" in capsys.readouterr().err
    assert main(["benchmark", "--methods", "oracle,foo", "--out", str(out)]) == 2
    assert "--methods: 'foo' is not among the catalogue's methods" in capsys.readouterr().err
    assert main(["benchmark", "--families", "nope", "--out", str(out)]) == 2
    assert "no family 'nope'" in capsys.readouterr().err
    assert main(["benchmark", "--seeds", "999", "--out", str(out)]) == 2
    assert "--seeds 999: the catalogue's heldout split has" in capsys.readouterr().err
    assert main(["benchmark", "--driven", "sees", "--catalogue", str(_catalogue(tmp_path)), "--out", str(out)]) == 2
    assert "--driven sees: family pullout names no CAV that sees its hidden actor" in capsys.readouterr().err
    assert not out.exists()


def test_the_benchmark_runs_on_a_local_dask_cluster(tmp_path: Path) -> None:
    """Two closed-loop runs (oracle and none, one configuration, one seed, 3 frames) as Dask tasks on a loopback
    LocalCluster; their files come back into the family's sweep and the leaderboard is written from them."""
    import subprocess
    import sys

    distributed = pytest.importorskip("distributed")
    cat = _catalogue(tmp_path, profiles={"quick": {"seeds": 1, "levels": [1], "methods": ["oracle", "none"]}})
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=True, host="127.0.0.1",
                                  dashboard_address=None, protocol="tcp") as cluster:
        out = tmp_path / "bench"
        r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "benchmark", "--catalogue", str(cat), "--set",
                            "duration_s=0.3", "--set", "cavs.count=2", "--bootstrap", "200", "--engine", "dask",
                            "--scheduler", cluster.scheduler_address, "--out", str(out)], capture_output=True,
                           text=True, cwd=REPO, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "2 at a time on the Dask cluster at tcp://127.0.0.1:" in r.stderr
    fam = out / "families" / "pullout"
    runs = sorted(p.parent.parent.name for p in fam.glob("runs/*/seed0/metrics.json"))
    assert len(runs) == 2 and all("arrival_offset_s=-1-1-" in p for p in runs)  # the middle offset, [1, 1]
    for p in fam.glob("runs/*/seed0/metrics.json"):  # (the sweep's Dask engine: v2vsim/study/cluster.py)
        m = json.loads(p.read_text())
        assert m["status"] == "complete" and m["frames"] == 3 and m["driving"]["method"] in ("oracle", "none")
        assert list(m["methods"]) == ["none"]  # control.perceive driving: the one map it drives on
        assert (p.parent / "report.md").stat().st_size > 0 and (p.parent / "sweep-run.log").stat().st_size > 0
    assert [x["method"] for x in json.loads((fam / "sweep.json").read_text())["rows"]] == ["none", "none"]
    assert (fam / "sweep_driving_control.method.png").stat().st_size > 0
    doc = json.loads((out / "leaderboard.json").read_text())
    overall = next(b for b in doc["boards"] if b["scope"] == "overall")
    assert overall["episodes"] == 1 and set(overall["methods"]) == {"oracle", "none"}
    assert (out / "leaderboard.md").read_text().startswith("# v2vsim closed-loop benchmark")


def test_driven_sees_drives_each_familys_seeing_cavs_beside_the_ego_and_they_are_placed_cavs() -> None:
    """`--driven sees` (issue 54): every shipped family names the CAVs that see its hidden actor; each is a placed,
    non-ego CAV of its scenario, and the variant's override makes the ego and them the scenario's egos."""
    from dataclasses import replace

    cat = load_catalogue()
    args = BenchmarkArgs(out=Path("b"), profile="quick", families=tuple(f.name for f in cat.families))
    plain = dict(family_sweeps(args, cat))
    seeing = dict(family_sweeps(replace(args, driven="sees"), cat))
    every = dict(family_sweeps(replace(args, driven="all"), cat))
    for f in cat.families:
        assert f.sees, f.name
        sc = load_scenario(f.scenario, list(seeing[f.name].overrides))
        placed = [f"cav{i}" for i in range(sc.cavs.count)]
        assert set(f.sees) <= set(placed) - {"cav0"}, f.name
        assert sc.cavs.egos_among(placed) == ["cav0", *f.sees]
        assert load_scenario(f.scenario, list(plain[f.name].overrides)).cavs.egos_among(placed) == ["cav0"]
        assert load_scenario(f.scenario, list(every[f.name].overrides)).cavs.egos_among(placed) == placed


def test_the_critical_actor_columns_become_leaderboard_measures() -> None:
    base = {"control.method": "cobevt", "seed": 0, "method": "cobevt", "status": "complete",
            "driving_method": "cobevt", "driving_driving_score": 1.0, "driving_success": 1, "driving_collisions": 0}
    rows = [{**base, "seed": 0, "driving_critical_missed": 0, "driving_critical_lead_time_s": 1.5,
             "driving_critical_detected_share": 0.8},
            {**base, "seed": 1, "driving_critical_missed": 1, "driving_critical_lead_time_s": None,
             "driving_critical_detected_share": None, "driving_success": 0},
            {**base, "seed": 2}]  # a family without a critical actor: no such columns
    eps = episodes_of("f", {"grid": [{"key": "control.method"}], "rows": rows})
    got = {e.seed: runs["cobevt"] for e, runs in eps.items()}
    assert (got[0]["critical_detected"], got[0]["critical_lead_s"], got[0]["critical_share"]) == (1.0, 1.5, 0.8)
    assert (got[1]["critical_detected"], got[1]["critical_lead_s"], got[1]["critical_share"]) == (0.0, 0.0, None)
    assert got[2]["critical_detected"] is None and got[2]["critical_lead_s"] is None


def test_close_calls_and_the_safety_score_come_from_the_row_or_from_its_ssm_figures() -> None:
    base = {"control.method": "none", "seed": 0, "method": "none", "status": "complete", "driving_method": "none",
            "driving_driving_score": 1.0, "driving_success": 1, "driving_collisions": 0, "driving_near_misses": 0}
    rows = [{**base, "seed": 0, "driving_close_calls": 1, "driving_safety_score": 0.7746},  # written by the ego
            {**base, "seed": 1, "driving_min_ttc_s": 2.1, "driving_min_pet_s": 0.9},  # before the fields: PET 0.9 s
            {**base, "seed": 2, "driving_min_ttc_s": 2.1, "driving_min_pet_s": 1.4, "driving_pet_s": 1.2},
            {**base, "seed": 3, "driving_collisions": 1, "driving_driving_score": 0.6, "driving_min_ttc_s": 0.0}]
    eps = episodes_of("f", {"grid": [{"key": "control.method"}], "rows": rows})
    got = {e.seed: (runs["none"]["close_call"], runs["none"]["safety_score"]) for e, runs in eps.items()}
    assert got[0] == (1.0, 0.7746) and got[2] == (0.0, 1.0) and got[3] == (0.0, 0.6)
    assert got[1][0] == 1.0 and got[1][1] == pytest.approx(0.7746, abs=1e-4)


def test_auc_is_the_chance_a_success_outscores_a_failure() -> None:
    assert auc([0.9, 0.8, 0.1, 0.2], [True, True, False, False]) == 1.0
    assert auc([0.1, 0.2, 0.9, 0.8], [True, True, False, False]) == 0.0
    assert auc([0.5, 0.5], [True, False]) == 0.5
    assert auc([0.3, 0.7, 0.5], [True, False, True]) == 0.0  # both successes below the failure
    assert auc([1.0], [True]) is None
