"""What the ego accepts on the wire for a scenario, and the one function it decodes with.

Every dimension is exact or bounded by the scenario, so the codec can refuse an oversized or
inflating message from its header alone (v2vsim.comm.codec "KindSpec"):

  features  (C / r, F, F) float16: the encoder's grid, exactly; the header must name the
            run's ratio r (perception.build.wire_ratio: comm.channel_compression or the zoo's;
            the ego's decoder is built for it)
  points    (<= lidar.channels * lidar.points_per_channel, 4) float32: one body-frame sweep
            (v2vsim.perception.encode.body_frame_points keeps at most one return per ray)
  outputs   (3, S, S) float16 maps at the heads' segmentation grid S (the preset's seg_cells, 256, whatever
            the fusion grid: the decoder upsamples a 32 x 32 map 8x, a 64 x 64 one 4x), and exactly one
            extra, "boxes" (<= MAX_BOXES, 6): x, y, l, w, yaw, score after NMS
  sparse    (N, C / r) float16, N <= F * F: the values of N cells of the features map (ratio r as
            for features), and exactly one extra, "cells" (N,) uint16/uint32: their row-major
            indices into the F x F grid, in range and strictly increasing (v2vsim.comm.sparse)
  points and outputs carry no channel compression (ratio 1); no other extra is accepted.

`EgoDecoder` is the ego's decode path for every kind: agents/ego.py calls it for each received
message and the fuzz test (tests/v2vsim/comm/test_fuzz.py) drives the same object.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass

from models.heads import MAX_DETECTIONS
from models.presets import get_preset
from v2vsim.comm.codec import CELLS, EVIDENCE, AtMost, KindSpec, Message, RejectedMessage, check_arrival, decode
from v2vsim.comm.stats import CommStats
from v2vsim.config import Scenario
from v2vsim.perception.evidence import evidence_cells, packed_size

MAX_BOXES = MAX_DETECTIONS
"""Late fusion ships at most this many boxes per CAV: models.heads.decode_detections' top_k."""

BOX_FIELDS = 6  # x, y, l, w, yaw, score (v2vsim.perception.encode.late_outputs)


KEY_KINDS = {"features": ("features", "sparse")}
"""The codec kinds each bus key carries where more than its own: a CAV under comm.share topk sends its
features as a "sparse" message on the same key (v2vsim.comm.share)."""


def message_kind(method: str) -> str | None:
    """The message kind a fusion method fuses (None: `none` fuses nothing)."""
    return {"early": "points", "late": "outputs", "none": None}.get(method, "features")


def ego_wire_spec(sc: Scenario, encoder_out_channels: int, encoder_out_cells: int, ratio: int | None = None,
                  spaces: frozenset[str] | None = None) -> dict[str, KindSpec]:
    """The KindSpec of each message kind the ego of `sc` may receive (see the module docstring); `ratio`: the
    run's channel compression (v2vsim.perception.build.wire_ratio; default comm.channel_compression or 1);
    `spaces`: the feature spaces a features/sparse message must name (a mixed fleet; None: any)."""
    c, f = encoder_out_channels, encoder_out_cells
    r = ratio if ratio is not None else (sc.comm.channel_compression or 1)
    s = get_preset(sc.perception.preset).seg_cells  # the late outputs' maps: the heads' grid, not 8 F
    sweep = sc.sensors.lidar.channels * sc.sensors.lidar.points_per_channel
    # defence.evidence: a LiDAR sender's free-space evidence beside its map (optional: a camera CAV has no rays)
    ev = {EVIDENCE: (packed_size(evidence_cells(f)),)} if sc.defence.evidence else {}
    return {
        "features": KindSpec((c // r, f, f), extras=ev, optional=frozenset(ev), channel_compression=r, spaces=spaces),
        "points": KindSpec((AtMost(sweep), 4)),
        "outputs": KindSpec((3, s, s), extras={"boxes": (AtMost(MAX_BOXES), BOX_FIELDS), **ev},
                            optional=frozenset(ev)),
        "sparse": KindSpec((AtMost(f * f), c // r), extras={CELLS: (AtMost(f * f),), **ev},
                           optional=frozenset(ev), channel_compression=r, cells=f * f, spaces=spaces),
    }


@dataclass(frozen=True)
class EgoDecoder:
    """Validates one received V2V message for the ego: its kind's spec, the run, the senders, the key."""

    spec: Mapping[str, KindSpec]
    run_id: str
    senders: Collection[str]
    key: bytes | None = None

    def _accepted(self, key: str) -> dict[str, KindSpec]:
        return {k: self.spec[k] for k in KEY_KINDS.get(key, (key,)) if k in self.spec}

    def max_bytes(self, kind: str) -> int:
        """The longest message `kind`'s key can carry and be accepted (longer ones need not even be kept)."""
        limits = [ks.max_message_bytes(k) for k, ks in self._accepted(kind).items()]
        return 0 if not limits or None in limits else max(limits)  # type: ignore[type-var]

    def decode(self, kind: str, data: bytes, sender: str | None = None, *, verified: bool = False) -> Message:
        """The message that arrived on `kind`'s key from `sender` (the key's last chunk, if known),
        or RejectedMessage(reason). The "features" key also carries "sparse" messages (KEY_KINDS).
        verified: these very bytes passed check_arrival, signature included (not checked twice)."""
        accepted = self._accepted(kind)
        if not accepted:
            raise RejectedMessage("unexpected_kind", f"nothing of kind {kind!r} is expected")
        msg = decode(data, key=None if verified else self.key, known_senders=self.senders, run_id=self.run_id,
                     spec=accepted)
        if sender is not None and msg.sender_id != sender:
            raise RejectedMessage("unknown_sender", f"{msg.sender_id!r} published under {sender!r}")
        return msg

    def check_arrival(self, kind: str, data: bytes, sender: str) -> int:
        """The frame of a message that just came off `kind`'s key from `sender`, after the cheap checks
        (header, signature under comm.auth, run, sender: codec.check_arrival); RejectedMessage otherwise.
        The ego runs this on zenoh's thread so that nothing forged or foreign takes a slot in its mailbox."""
        if not self._accepted(kind):
            raise RejectedMessage("unexpected_kind", f"nothing of kind {kind!r} is expected")
        frame, claimed = check_arrival(data, key=self.key, run_id=self.run_id, known_senders=self.senders)
        if claimed != sender:
            raise RejectedMessage("unknown_sender", f"{claimed!r} published under {sender!r}")
        return frame

    def receive(self, kind: str, data: bytes, sender: str | None, stats: Iterable[CommStats], *,
                verified: bool = False) -> Message | None:
        """decode(), with a rejection counted (by reason) in every `stats` instead of raised."""
        try:
            return self.decode(kind, data, sender, verified=verified)
        except RejectedMessage as e:
            for s in stats:
                s.record_rejected(e.reason)
            return None
