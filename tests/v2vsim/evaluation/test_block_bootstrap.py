"""The run's difference to `none` with a moving-block bootstrap interval over frames: the statistics on
synthetic counts with a known difference, the block length rule, and what metrics.json / report.md say."""

from __future__ import annotations

import numpy as np
import pytest

from v2vsim.comm.stats import CommStats
from v2vsim.config import scenario_from_dict
from v2vsim.evaluation.block_bootstrap import block_length, first_uncorrelated_lag, paired_difference
from v2vsim.evaluation.metrics import MethodScore, paired_counts
from v2vsim.evaluation.metrics_doc import metrics_json
from v2vsim.evaluation.report_md import report_md
from v2vsim.evaluation.run_summary import RunSummary

UNION = 1000  # cells in each frame's union: IoU = intersection / 1000


def _ar1(phi: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """A stationary AR(1) series with unit innovations."""
    e = rng.normal(size=n)
    x = np.empty(n)
    x[0] = e[0] / np.sqrt(1 - phi**2)
    for t in range(1, n):
        x[t] = phi * x[t - 1] + e[t]
    return x


def _counts(intersections: np.ndarray) -> np.ndarray:
    return np.c_[np.round(intersections), np.full(len(intersections), UNION)]


def _independent_frames(seed: int, n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, a union of 200-800 cells; the method hits 60% of it, none 50%: true difference 0.1."""
    rng = np.random.default_rng(seed)
    u = rng.integers(200, 800, size=n)
    return np.c_[rng.binomial(u, 0.6), u], np.c_[rng.binomial(u, 0.5), u]


def test_interval_covers_a_known_difference_and_excludes_zero() -> None:
    a, b = _independent_frames(0)
    d = paired_difference(a, b)
    assert d is not None
    assert d.diff == pytest.approx(a[:, 0].sum() / a[:, 1].sum() - b[:, 0].sum() / b[:, 1].sum())
    assert d.low < 0.1 < d.high and d.excludes_zero
    assert d.high - d.low < 0.02  # 400 frames of ~500 cells: the interval is tight
    # over 100 such runs the 95% interval covers the true difference about 95 times in 100
    covered = 0
    for seed in range(100):
        r = paired_difference(*_independent_frames(seed), replicates=500)
        assert r is not None
        covered += r.low <= 0.1 <= r.high
    assert covered >= 88
    # the same method against itself: a zero difference whose interval covers 0
    same = paired_difference(a, a)
    assert same is not None and same.diff == 0 and not same.excludes_zero


def test_coverage_on_autocorrelated_frames_beats_the_frame_by_frame_bootstrap() -> None:
    # 80 runs of AR(1) frames (phi 0.8) with a true difference of 0.1: the chosen blocks cover it in most
    # runs; drawing frames one by one (block 1) ignores the correlation and covers it far less often
    n, phi, runs = 300, 0.8, 80
    hits = {None: 0, 1: 0}
    for seed in range(runs):
        rng = np.random.default_rng(seed)
        a, b = _counts(600 + 20 * _ar1(phi, n, rng)), _counts(500 + 20 * _ar1(phi, n, rng))
        for block in hits:
            d = paired_difference(a, b, block=block, replicates=500)
            assert d is not None
            hits[block] += d.low <= 0.1 <= d.high
    assert hits[None] / runs >= 0.75
    assert hits[1] / runs <= hits[None] / runs - 0.15


def test_a_constant_series_gives_a_zero_width_interval() -> None:
    a = np.tile([[7, 10]], (30, 1))
    b = np.tile([[4, 10]], (30, 1))
    d = paired_difference(a, b)
    assert d is not None
    assert d.low == d.high == d.diff == pytest.approx(0.3)
    assert first_uncorrelated_lag(np.zeros(30), 7) == 1


def test_autocorrelated_frames_get_longer_blocks_and_a_wider_interval_than_shuffled() -> None:
    rng = np.random.default_rng(0)
    n = 500
    a, b = _counts(600 + 30 * _ar1(0.9, n, rng)), _counts(np.full(n, 500.0))
    shuffle = rng.permutation(n)  # the same values, the order (and so the correlation) gone
    corr, iid = paired_difference(a, b), paired_difference(a[shuffle], b[shuffle])
    assert corr is not None and iid is not None
    assert corr.diff == pytest.approx(iid.diff)
    assert iid.block == 8  # ceil(500^(1/3)): no correlation left to lengthen it
    assert corr.block > 2 * iid.block
    assert corr.high - corr.low > 2 * (iid.high - iid.low)


def test_block_length_rule() -> None:
    assert block_length(np.arange(1000.0) % 2) == 10  # alternating: lag 1 is negative; ceil(1000^(1/3))
    assert block_length(np.arange(1000.0)) == 250  # a trend is correlated at every lag: the cap n // 4
    assert block_length(np.arange(64.0) % 2) == 4  # 64^(1/3) = 4 exactly, not 5 from float error
    assert block_length(np.array([1.0, 2.0, 3.0])) == 1  # n // 4 = 0: blocks of one frame


def test_deterministic_for_the_same_counts_and_seed() -> None:
    rng = np.random.default_rng(5)
    a, b = _counts(600 + 20 * _ar1(0.5, 200, rng)), _counts(550 + 20 * _ar1(0.5, 200, rng))
    first, again = paired_difference(a, b), paired_difference(a.copy(), b.copy())
    assert first == again
    other = paired_difference(a, b, seed=1)  # the generator is used: another seed, other replicates
    assert other is not None and first is not None and (other.low, other.high) != (first.low, first.high)


def test_tiny_or_empty_runs_give_no_interval() -> None:
    one = np.array([[3, 5]])
    assert paired_difference(one, one) is None  # one frame: nothing to resample
    assert paired_difference(np.zeros((0, 2)), np.zeros((0, 2))) is None
    empty = np.zeros((10, 2), dtype=int)  # no union in any frame: the IoU does not exist
    assert paired_difference(empty, np.tile([[3, 5]], (10, 1))) is None
    assert paired_difference(np.tile([[3, 5]], (10, 1)), empty) is None
    with pytest.raises(ValueError, match="same frames"):
        paired_difference(np.tile([[3, 5]], (10, 1)), np.tile([[3, 5]], (9, 1)))


def _gt(hit_cells: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """A 4 x 8 frame: 8 vehicle cells in row 0, a road of rows 0-1, a lane of row 1; the prediction hits
    `hit_cells` of the vehicle cells. Returns (gt, vehicle probabilities)."""
    z = np.zeros((4, 8), bool)
    gt = {"dynamic": z.copy(), "visible": z.copy(), "road": z.copy(), "lane": z.copy()}
    gt["dynamic"][0] = gt["visible"][0] = True
    gt["road"][:2] = True
    gt["lane"][1] = True
    p = np.zeros((4, 8), np.float32)
    p[0, :hit_cells] = 0.9
    return gt, p


def _scores(frames: int, skip_late: int | None = None) -> dict[str, MethodScore]:
    """none hits 2-3 of 8 vehicle cells, late 5-7 (both perfect on road and lane); late misses frame
    `skip_late` (no input), as a realtime ego's method can."""
    scores = {"none": MethodScore(), "late": MethodScore()}
    for k in range(frames):
        # frame-to-frame variation, out of step between the methods so that their difference varies too
        for m, hit in (("none", 2 + k % 2), ("late", 6 + (k % 3 == 1) - (k % 3 == 2))):
            if m == "late" and k == skip_late:
                continue
            gt, p = _gt(hit)
            scores[m].add_segmentation({"vehicle": p, "road": gt["road"].astype(np.float32),
                                        "lane": gt["lane"].astype(np.float32)}, gt, frame=k)
    return scores


def _summary(methods: list[str]) -> RunSummary:
    sc = scenario_from_dict({"traffic": {"backend": "highway-env"}, "cavs": {"count": 2}})
    return RunSummary(scenario=sc, ego="cav0", methods=methods, untrained=True, frames=40, wall_s=1.0)


def test_methods_pair_on_frame_keys_not_positions() -> None:
    scores = _scores(6, skip_late=2)
    a, b = paired_counts(scores["late"].vehicle, scores["none"].vehicle)
    assert len(a) == len(b) == 5
    # frame 3 follows frame 1 in both: rows are the same frames, not the same positions
    assert a[:, 0].tolist() == [6, 7, 6, 7, 5] and b[:, 0].tolist() == [2, 3, 3, 2, 3]
    assert scores["late"].to_json(None)["iou_vehicle_frames"] == [0, 1, 3, 4, 5]


def test_metrics_json_and_report_carry_the_difference_to_none() -> None:
    scores = _scores(40)
    summary = _summary(["none", "late"])
    doc = metrics_json(summary, scores, CommStats(), {}, None)
    assert "vs_none" not in doc["methods"]["none"]
    v = doc["methods"]["late"]["vs_none"]
    assert v["replicates"] == 2000 and v["level"] == 0.95
    veh = v["iou_vehicle"]
    assert veh["diff"] == pytest.approx(doc["methods"]["late"]["iou_vehicle"] - doc["methods"]["none"]["iou_vehicle"],
                                        abs=1e-4)
    # (240 - 100) / 320 hit cells over the 40 frames: 0.4375
    assert veh["diff"] == pytest.approx(0.4375) and veh["low"] < veh["diff"] < veh["high"]
    assert veh["excludes_zero"]
    assert veh["frames"] == 40 and veh["block_frames"] == 4  # ceil(40^(1/3)) = 4 = n // 4
    # road and lane are perfect in both: a difference of exactly 0 that the interval cannot exclude
    assert v["iou_road"]["diff"] == 0 and v["iou_road"]["low"] == v["iou_road"]["high"] == 0
    assert not v["iou_lane"]["excludes_zero"]
    md = report_md(doc, summary)
    assert "### Difference to no fusion (95 % moving-block bootstrap over frames)" in md
    row = f"| late | {100 * veh['diff']:+.1f} [{100 * veh['low']:+.1f}, {100 * veh['high']:+.1f}] * | " \
          "+0.0 [+0.0, +0.0] | +0.0 [+0.0, +0.0] | 4 / 4 / 4 |"
    assert row in md
    # near the method table: after it, before the communication section
    assert md.index("## Methods") < md.index("Difference to no fusion") < md.index("## Communication")


def test_without_none_or_frames_there_is_no_interval() -> None:
    scores = _scores(40)
    del scores["none"]
    summary = _summary(["late"])
    doc = metrics_json(summary, scores, CommStats(), {}, None)
    assert doc["methods"]["late"]["vs_none"] is None
    assert "Difference to no fusion" not in report_md(doc, summary)
    one = metrics_json(_summary(["none", "late"]), _scores(1), CommStats(), {}, None)
    v = one["methods"]["late"]["vs_none"]
    assert v["iou_vehicle"] is None and v["iou_road"] is None
    assert "| late | - | - | - | - / - / - |" in report_md(one, _summary(["none", "late"]))
