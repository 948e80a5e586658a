"""Trust that remembers (v2vsim/perception/reputation.py): a flag takes any sender out, it comes back after the
judged clean frames the beta reputation asks, later when it lied more, and never while nobody can judge it."""

from __future__ import annotations

import pytest

from v2vsim.perception.reputation import Standing, update

FORGET, WEIGHT = 0.95, 10.0


def _frames_to_return(st: Standing, judged: bool = True, limit: int = 200) -> int | None:
    for k in range(1, limit + 1):
        st = update(st, judged, False, FORGET, WEIGHT)
        if st.trusted:
            return k
    return None


def test_a_new_sender_is_trusted_and_one_flag_takes_it_out_for_eight_clean_frames() -> None:
    st = Standing()
    assert st.trusted and st.reputation == 0.5
    flagged = update(st, True, True, FORGET, WEIGHT)
    assert not flagged.trusted and flagged.reputation == pytest.approx(1 / 12)
    assert _frames_to_return(flagged) == 8


def test_an_honest_past_buys_nothing_and_lying_more_keeps_it_out_longer() -> None:
    veteran = Standing()
    for _ in range(500):
        veteran = update(veteran, True, False, FORGET, WEIGHT)
    assert veteran.reputation > 0.95
    once = update(veteran, True, True, FORGET, WEIGHT)
    assert not once.trusted and _frames_to_return(once) == 8  # the same as a newcomer's
    thrice = once
    for _ in range(2):
        thrice = update(thrice, True, True, FORGET, WEIGHT)
    assert _frames_to_return(thrice) > 15


def test_a_sender_nobody_can_judge_earns_nothing_back() -> None:
    flagged = update(Standing(), True, True, FORGET, WEIGHT)
    assert _frames_to_return(flagged, judged=False) is None
