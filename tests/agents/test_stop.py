"""Ctrl-C in an agent (agents.lifecycle.Stop) is never mistaken for a bad message: the codec turns every Exception
of a decode into a rejection, and a Stop raised by the signal handler in the middle of one used to become a
`bad_header` rejection (seen as one spurious rejection in an interrupted run), with the agent carrying on."""

from __future__ import annotations

import pytest

from agents.lifecycle import Stop
from v2vsim.comm import codec
from v2vsim.comm.codec import RejectedMessage


def _interrupted(*args: object, **kwargs: object) -> None:
    raise Stop(2)  # what the SIGINT handler raises wherever the main thread is


def _broken(*args: object, **kwargs: object) -> None:
    raise KeyError("a bug")


def test_a_stop_inside_a_decode_stops_the_agent(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(codec, "_decode", _interrupted)
    with pytest.raises(Stop):
        codec.decode(b"whatever", expected={})


def test_a_bug_inside_a_decode_is_still_a_rejection(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(codec, "_decode", _broken)
    with pytest.raises(RejectedMessage, match="internal: KeyError") as e:
        codec.decode(b"whatever", expected={})
    assert e.value.reason == "bad_header"
