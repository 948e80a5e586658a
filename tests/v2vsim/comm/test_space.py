"""A mixed fleet's feature messages name their encoder and feature space (Message.space, the FLAG_SPACE header
field); a receiver that fuses one space rejects a message of another, or of none, as 'foreign_space' and counts it;
a message without a space keeps the wire bytes of every single-encoder run."""

from __future__ import annotations

import numpy as np
import pytest

from v2vsim.comm.codec import FLAG_SPACE, KindSpec, Message, RejectedMessage, decode, encode
from v2vsim.comm.stats import CommStats
from v2vsim.comm.wire_spec import EgoDecoder

RUN = "run-48"
BASE = "pointpillars_tiny:f487cbd52552"


def features(space: str = "", shape: tuple[int, ...] = (8, 16, 16)) -> Message:
    rng = np.random.default_rng(0)
    return Message(kind="features", run_id=RUN, sender_id="cav2", frame=5, capture_time=0.5,
                   sender_pose=(1.0, 2.0, 0.0, 0.3), payload=rng.standard_normal(shape).astype(np.float32), space=space)


def test_space_round_trips_and_costs_only_its_text() -> None:
    plain, named = encode(features()), encode(features(f"sinbevt@{BASE}"))
    assert plain[6] & FLAG_SPACE == 0 and named[6] & FLAG_SPACE
    assert len(named) == len(plain) + 2 + len(f"sinbevt@{BASE}")
    got = decode(named, spec={"features": KindSpec((8, 16, 16), spaces=frozenset({BASE}))})
    assert got.space == f"sinbevt@{BASE}"
    np.testing.assert_array_equal(got.payload, decode(plain).payload)
    assert decode(plain).space == ""


def test_unnamed_message_is_the_single_encoder_layout() -> None:
    """No space: the header holds no space field and no flag, byte for byte the layout of before (fixed header,
    run id, sender id, one array, the payload; 56 bytes of fixed header: "<4sBBBBHHIddddd")."""
    data = encode(features())
    header = 56 + 2 + len(RUN) + 2 + len("cav2") + 1 + 0 + 2 + 3 * 4 + 4
    assert len(data) == header + 8 * 16 * 16 * 2
    assert data[6] == 0


@pytest.mark.parametrize("space", ["sinbevt@sinbevt_tiny:0123456789ab", "", "pointpillars@pointpillars_tiny:other"])
def test_another_space_or_none_is_foreign(space: str) -> None:
    with pytest.raises(RejectedMessage) as e:
        decode(encode(features(space)), spec={"features": KindSpec((8, 16, 16), spaces=frozenset({BASE}))})
    assert e.value.reason == "foreign_space"
    assert BASE in e.value.detail


def test_foreign_space_is_checked_before_the_shape() -> None:
    """A camera zoo's own 32 x 32 map (another space, another shape) is foreign, not a shape mismatch: the report
    says why it was not fused."""
    msg = features("sinbevt@sinbevt_tiny:0123456789ab", shape=(64, 32, 32))
    with pytest.raises(RejectedMessage) as e:
        decode(encode(msg), spec={"features": KindSpec((8, 16, 16), spaces=frozenset({BASE}))})
    assert e.value.reason == "foreign_space"


def test_ego_decoder_counts_a_foreign_message_and_carries_on() -> None:
    dec = EgoDecoder({"features": KindSpec((8, 16, 16), spaces=frozenset({BASE}))}, RUN, frozenset({"cav2"}))
    stats = CommStats()
    assert dec.receive("features", encode(features("sinbevt@sinbevt_tiny:0123456789ab")), "cav2", [stats]) is None
    assert dec.receive("features", encode(features(f"sinbevt@{BASE}")), "cav2", [stats]) is not None
    assert stats.rejected == 1 and stats.to_json()["rejected_reasons"] == {"foreign_space": 1}


def test_any_space_is_accepted_without_spaces() -> None:
    """A receiver outside a mixed fleet (spaces None) reads a named message as before."""
    got = decode(encode(features(f"lara@{BASE}")), spec={"features": KindSpec((8, 16, 16))})
    assert got.space == f"lara@{BASE}"
