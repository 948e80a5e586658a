"""CommStats: the metrics.json `comm` shape, percentiles, merging across processes."""

from __future__ import annotations

import json

import pytest

from v2vsim.comm.channel import Delivery
from v2vsim.comm.stats import CommStats

CONTRACT_KEYS = ["sent", "delivered", "dropped", "stale", "rejected", "bytes_per_message", "latency_ms"]


def test_empty() -> None:
    j = CommStats().to_json()
    assert list(j)[:7] == CONTRACT_KEYS
    assert j["latency_ms"] == {"p50": None, "p95": None} and j["bytes_per_message"] == 0
    json.dumps(j)


def test_counts_and_percentiles() -> None:
    s = CommStats()
    for n in (100, 200, 300):
        s.record_sent(n)
    s.record_sent(400, copies=2)
    s.record_channel(Delivery(True, "ok", 0.1, 0.0))
    s.record_channel(Delivery(False, "dropped", float("inf")))
    s.record_channel(Delivery(False, "out_of_range", float("inf")))
    s.record_stale()
    s.record_rejected("bad_signature")
    s.record_rejected("bad_signature")
    s.record_rejected("truncated")
    for ms in range(1, 101):
        s.record_fused(ms / 1000)
    s.record_lost_agent("cav3")
    j = s.to_json()
    assert j["sent"] == 5 and j["bytes_per_message"] == round(1400 / 5) and j["bytes_total"] == 1400
    assert (j["delivered"], j["dropped"], j["out_of_range"], j["stale"], j["rejected"]) == (1, 1, 1, 1, 3)
    assert j["rejected_reasons"] == {"bad_signature": 2, "truncated": 1}
    assert j["latency_ms"]["p50"] == pytest.approx(50.5) and j["latency_ms"]["p95"] == pytest.approx(95.05)
    assert j["lost_agents"] == ["cav3"]
    json.dumps(j)


def test_merge_and_state_round_trip() -> None:
    a, b = CommStats(), CommStats()
    a.record_sent(1000)
    a.record_sent(1000)
    b.record_channel(Delivery(True, "ok", 0.2, 0.1))
    b.record_fused(0.1)
    b.record_rejected("unknown_sender")
    merged = CommStats.from_state(json.loads(json.dumps(a.to_state()))).merge(CommStats.from_state(b.to_state()))
    j = merged.to_json()
    assert (j["sent"], j["delivered"], j["rejected"], j["bytes_per_message"]) == (2, 1, 1, 1000)
    assert j["latency_ms"]["p50"] == pytest.approx(100.0)
    assert "los" not in j and "delivery_by_distance" not in j  # disk: no link-state keys


def test_link_states_merge_and_state_round_trip() -> None:
    a, b = CommStats(), CommStats()
    a.record_channel(Delivery(True, "ok", 0.1, 0.0, "los", 30.0), 10.0)
    a.record_channel(Delivery(False, "dropped", float("inf"), 0.0, "nlos", 2.0), 30.0)
    a.record_channel(Delivery(False, "out_of_range", float("inf")), 90.0)  # no state: not in the bins
    b.record_channel(Delivery(True, "ok", 0.1, 0.0, "los", 20.0), 24.9)
    b.record_channel(Delivery(True, "ok", 0.1, 0.0, "nlosv", 9.0), 49.0)
    b.record_channel(Delivery(False, "dropped", float("inf"), 0.0, "nlosv", 1.0), 26.0)
    old = a.to_state()
    del old["link_states"], old["by_distance"]  # a state written before tr37885
    assert "los" not in CommStats.from_state(old).to_json()
    merged = CommStats.from_state(json.loads(json.dumps(a.to_state()))).merge(CommStats.from_state(b.to_state()))
    j = merged.to_json()
    assert (j["los"], j["nlos"], j["nlosv"], j["out_of_range"]) == (2, 1, 2, 1)
    assert j["delivery_by_distance"] == {
        "los": {"0-25": {"sent": 2, "delivered": 2, "ratio": 1.0}},
        "nlos": {"25-50": {"sent": 1, "delivered": 0, "ratio": 0.0}},
        "nlosv": {"25-50": {"sent": 2, "delivered": 1, "ratio": 0.5}},
    }
    tracked = CommStats()
    tracked.track_link_states()
    assert (tracked.to_json()["los"], tracked.to_json()["delivery_by_distance"]["los"]) == (0, {})
    assert "los" in CommStats().merge(tracked).to_json()
    json.dumps(j)
