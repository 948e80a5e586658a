"""Signed control messages (v2vsim.comm.control): what a key holder sends is accepted, and nothing
else is: no signature, another run, another kind, another sender, a replay, any flipped bit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from v2vsim.comm.codec import REASONS, RejectedMessage
from v2vsim.comm.control import (
    CONTROL_KINDS,
    ControlPolicy,
    ReplayGuard,
    open_sealed,
    seal,
)

KEY = b"run key 0123"
RUN = "run-1"
POLICY = ControlPolicy.for_run(["cav0", "cav1"], ["cav0"])


def reason(data: bytes, kind: str = "done", key_sender: str = "main", run_id: str = RUN,
           key: bytes = KEY) -> str:
    with pytest.raises(RejectedMessage) as ei:
        open_sealed(key, run_id, kind, key_sender, data, POLICY)
    assert ei.value.reason in REASONS
    return ei.value.reason


def test_round_trip() -> None:
    done = json.dumps({"frames": 40}).encode()
    got = open_sealed(KEY, RUN, "done", "main", seal(KEY, RUN, "done", "driver.main", 3, done), POLICY)
    assert (got.sender, got.seq, got.payload) == ("driver.main", 3, done)
    ack = seal(KEY, RUN, "ack", "ego.cav0", 0, b'{"ego": "cav0", "frame": 0}')
    assert open_sealed(KEY, RUN, "ack", "cav0", ack, POLICY).sender == "ego.cav0"
    static = seal(KEY, RUN, "static", "driver.main", 0, b"")
    assert open_sealed(KEY, RUN, "static", "main", static, POLICY).payload == b""


def test_the_issues_two_bytes_are_unsigned() -> None:
    """Issue 8 item 3: `{}` on the done key cut a 40-frame run to 8 frames."""
    assert reason(b"{}") == "unsigned"
    assert reason(b"") == "unsigned"
    assert reason(json.dumps({"frames": 40}).encode()) == "unsigned"


def test_another_run_kind_key_or_sender_is_refused() -> None:
    done = seal(KEY, RUN, "done", "driver.main", 0, b"{}")
    assert reason(done, run_id="run-2") == "bad_signature"  # a recording of another run
    assert reason(done, key=b"another key") == "bad_signature"
    ack = seal(KEY, RUN, "ack", "ego.cav0", 5, b"{}")
    assert reason(ack, kind="done", key_sender="cav0") == "bad_signature"  # a signed ack replayed as done
    # signed, but by a process that may not send this kind, or under another process's key
    assert reason(seal(KEY, RUN, "done", "cav.cav1", 0, b"{}"), key_sender="cav1") == "unknown_sender"
    assert reason(seal(KEY, RUN, "world", "ego.cav0", 0, b"{}"), kind="world", key_sender="cav0") == "unknown_sender"
    assert reason(seal(KEY, RUN, "vis", "ego.cav0", 0, b"{}"), kind="vis", key_sender="cav0") == "unknown_sender"
    assert reason(seal(KEY, RUN, "ack", "ego.cav1", 0, b"{}"), kind="ack", key_sender="cav1") == "unknown_sender"
    assert reason(done, key_sender="cav0") == "unknown_sender"  # published under someone else's key
    assert POLICY.allows("vis", "cav.cav1") and POLICY.allows("bye", "ego.cav0") and not POLICY.allows("x", "a")


def test_replays_are_refused() -> None:
    guard = ReplayGuard()
    msgs = [open_sealed(KEY, RUN, "ack", "cav0", seal(KEY, RUN, "ack", "ego.cav0", i, b"{}"), POLICY)
            for i in range(3)]
    guard.check("ack", msgs[0])
    guard.check("ack", msgs[2])
    for old in (msgs[0], msgs[1], msgs[2]):
        with pytest.raises(RejectedMessage) as ei:
            guard.check("ack", old)
        assert ei.value.reason == "replayed"
    guard.check("world", msgs[0])  # counted per kind


def test_every_mutation_is_rejected() -> None:
    rng = np.random.default_rng(5)
    good = seal(KEY, RUN, "world", "driver.main", 7, json.dumps({"frame": 7, "actors": []}).encode())
    open_sealed(KEY, RUN, "world", "main", good, POLICY)
    seen = set()
    for i in range(len(good) * 8):
        data = bytearray(good)
        data[i // 8] ^= 1 << (i % 8)
        seen.add(reason(bytes(data), kind="world"))
    for n in range(len(good)):
        seen.add(reason(good[:n], kind="world"))
    for _ in range(500):
        seen.add(reason(rng.bytes(int(rng.integers(0, 200))), kind="world"))
        seen.add(reason(b"V2VC" + rng.bytes(int(rng.integers(0, 200))), kind="world"))
    assert {"unsigned", "truncated", "bad_signature", "bad_version"} <= seen, seen


def test_control_kinds() -> None:
    assert {"world", "done", "ack", "static", "start", "vis", "scan", "bye", "hello"} == CONTROL_KINDS
    assert not {"features", "points", "outputs"} & CONTROL_KINDS
