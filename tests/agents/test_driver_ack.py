"""agents.driver.parse_ack: what the driver takes from an ego's ack, and the forged commands it refuses (each a
RejectedMessage the Bus counts, never a crash and never a command applied to the vehicle)."""

from __future__ import annotations

import json

import pytest

from agents.driver import MAX_COMMAND_MPS2, parse_ack
from v2vsim.comm.codec import RejectedMessage


def _ack(**doc: object) -> bytes:
    return json.dumps(doc).encode()


def test_a_plan_is_taken_in_a_closed_loop_and_ignored_in_an_open_one() -> None:
    assert parse_ack(_ack(ego="cav0", frame=4, command={"accel": -2.5}), published=5, closed_loop=True) == (4, -2.5)
    assert parse_ack(_ack(ego="cav0", frame=4, command={"accel": -2.5}), published=5, closed_loop=False) == (4, None)
    assert parse_ack(_ack(ego="cav0", frame=5), published=5, closed_loop=True) == (5, None)


@pytest.mark.parametrize("command", [
    {"accel": float("nan")}, {"accel": float("inf")}, {"accel": -float("inf")},
    {"accel": MAX_COMMAND_MPS2 + 0.1}, {"accel": -1e9},
    {"accel": "brake"}, {"accel": None}, {"speed": 3.0}, "accel", [1.0],
])
def test_a_forged_or_broken_command_is_refused(command: object) -> None:
    # json.dumps writes NaN and Infinity, which json.loads reads back: a sender can put them on the wire
    with pytest.raises(RejectedMessage) as e:
        parse_ack(_ack(ego="cav0", frame=3, command=command), published=5, closed_loop=True)
    assert e.value.reason == "bad_header"


def test_an_ack_from_the_future_or_without_a_frame_is_refused() -> None:
    with pytest.raises(RejectedMessage) as e:
        parse_ack(_ack(ego="cav0", frame=10**6, command={"accel": 1.0}), published=5, closed_loop=True)
    assert e.value.reason == "out_of_window"
    for bad in (b"not json", _ack(ego="cav0"), _ack(frame="x"), b"[]"):
        with pytest.raises(RejectedMessage) as e:
            parse_ack(bad, published=5, closed_loop=True)
        assert e.value.reason == "bad_header"
