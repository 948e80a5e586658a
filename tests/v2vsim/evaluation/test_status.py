"""Issue 45: a run's status tells the truth (v2vsim.evaluation.status): lost agents and methods without a score
make a run that went through every frame "degraded: ...", grouped for a reader; other endings stay as they are."""

from __future__ import annotations

import pytest

from v2vsim.evaluation.status import (
    COMPLETE,
    cav_ranges,
    explain,
    final_status,
    finished,
    is_degraded,
    lost_text,
    terminal_line,
    unscored,
)


def test_consecutive_cavs_are_grouped_and_the_rest_listed_in_numeric_order() -> None:
    assert cav_ranges(["cav3", "cav1", "cav2"]) == "cav1-cav3"
    assert cav_ranges(["cav1", "cav2"]) == "cav1, cav2"  # two: a list reads better than a range
    assert cav_ranges(["cav10", "cav9", "cav0", "cav4", "cav5", "cav6", "cav7"]) == "cav0, cav4-cav7, cav9, cav10"
    assert cav_ranges(["cav2", "cav2"]) == "cav2"
    assert cav_ranges(["ego", "cav01", "cav1"]) == "cav1, cav01, ego"  # no number (or a padded one): as given


def test_lost_cavs_are_grouped_by_the_frame_they_were_lost_at() -> None:
    assert lost_text({"cav1": 6, "cav2": 6, "cav3": 6}) == "cav1-cav3 lost from frame 6"
    assert lost_text({"cav5": 9, "cav1": 6, "cav3": 6, "cav2": 6}) == \
        "cav1-cav3 lost from frame 6, cav5 lost from frame 9"


def test_a_complete_run_that_lost_agents_or_scored_nothing_is_degraded() -> None:
    assert final_status(COMPLETE, {}, []) == COMPLETE
    assert final_status(COMPLETE, {"cav2": 12}, []) == "degraded: cav2 lost from frame 12"
    # the fake ego token: every CAV lost at frame 0 and no method scored
    assert final_status(COMPLETE, {f"cav{i}": 0 for i in range(4)}, ["none", "cobevt"]) == \
        "degraded: cav0-cav3 lost from frame 0; methods with no score: none, cobevt"
    assert final_status(COMPLETE, {}, ["late"]) == "degraded: methods with no score: late"


@pytest.mark.parametrize("ended", ["ended early: the driver finished after frame 5", "driver died after frame 3",
                                   "stalled after frame 2: no world for 60 s from the driver",
                                   "interrupted after 4 frames", "crashed at frame 1: ValueError: x",
                                   "ego cav0 left the simulation at frame 9"])
def test_a_run_that_did_not_go_through_its_frames_keeps_its_own_status(ended: str) -> None:
    assert final_status(ended, {"cav1": 2}, ["cobevt"]) == ended
    assert not finished(ended) and not is_degraded(ended) and explain(ended) is None


def test_no_score_means_every_iou_null_not_one() -> None:
    assert unscored({"none": (0.5, 0.4, 0.8, 0.3), "late": (None, None, None, None),
                     "cobevt": (None, 0.2, 0.7, 0.4)}) == ["late"]  # no visible vehicle: no vehicle IoU, no fault


def test_finished_statuses_are_complete_and_degraded() -> None:
    assert finished(COMPLETE) and finished("degraded: cav1 lost from frame 3")
    assert not finished("running") and not finished(None) and not finished("degraded")
    assert "Degraded" in str(explain("degraded: cav1 lost from frame 3"))


def test_the_runners_last_line_says_what_happened() -> None:
    assert terminal_line({"cav0": COMPLETE}, "r/report.md") == "v2vsim: done: r/report.md"
    assert terminal_line({"cav0": "degraded: cav2 lost from frame 12"}, "r/report.md") == \
        "v2vsim: done, not complete: degraded: cav2 lost from frame 12; report: r/report.md"
    assert terminal_line({"cav0": COMPLETE, "cav1": "degraded: cav2 lost from frame 12"}, "r/report.md") == \
        "v2vsim: done, not complete: ego cav1: degraded: cav2 lost from frame 12; report: r/report.md"


def test_a_run_degraded_only_by_flagged_senders_went_as_configured() -> None:
    from v2vsim.evaluation.status import as_configured

    flagged = final_status(COMPLETE, {}, [], {"cav1": (57, 100), "cav2": (3, 90)})
    assert flagged == "degraded: cav1 disagreed in 57 of 100 frames; cav2 disagreed in 3 of 90 frames"
    assert as_configured(flagged) and as_configured(COMPLETE)
    lost_too = final_status(COMPLETE, {"cav3": 4}, [], {"cav1": (5, 9)})
    assert lost_too == "degraded: cav3 lost from frame 4; cav1 disagreed in 5 of 9 frames"
    assert not as_configured(lost_too)
    assert not as_configured("degraded: methods with no score: late")
    assert not as_configured("interrupted after 3 frames")
    assert not as_configured(None)


def test_the_report_explains_a_flagged_sender_without_telling_to_drop_the_run() -> None:
    from v2vsim.evaluation.status import explain

    flagged = explain("degraded: cav1 disagreed in 46 of 57 frames")
    assert flagged is not None and "`defence`" in flagged and "a sweep counts its scores" in flagged
    lost = explain("degraded: cav2 lost from frame 12; cav1 disagreed in 5 of 9 frames")
    assert lost is not None and "leave it out of comparisons" in lost
