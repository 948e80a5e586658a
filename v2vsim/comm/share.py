"""What a CAV shares of its BEV features, and how a receiver restores the map (comm.share).

The sender ranks its feature cells by its own single-agent vehicle confidence (Where2comm's spatial
confidence map, Eq. 2: the map says where objects are, so those cells are worth the bytes) and sends the
top `fraction` of them as a "sparse" message (indices + values, v2vsim.comm.sparse), or the whole map as a
"features" message when that is no larger on the wire. The receiver scatters a sparse message back into
a full map, zeros where nothing was sent, so every fusion method takes it unchanged.
"""

from __future__ import annotations

import numpy as np

from v2vsim.comm.codec import Message
from v2vsim.comm.sparse import gather, scatter, select_cells, sparse_is_smaller


def feature_message(payload: np.ndarray, confidence: np.ndarray | None, fraction: float, stamp: dict,
                    channel_compression: int = 1, extras: dict[str, np.ndarray] | None = None) -> Message:
    """The message carrying `fraction` of `payload` [C', F, F] (already channel-compressed).

    confidence: [F, F] the sender ranks its cells by (needed when fraction < 1). stamp: the Message
    fields every kind shares (run_id, sender_id, frame, capture_time, sender_pose, compression).
    fraction 0 is an empty sparse message: in a lockstep run it tells the receiver that frame k has
    nothing for it. extras: sent beside the map either way (the sender's free-space evidence)."""
    c, f, _ = payload.shape
    extras = dict(extras or {})
    if fraction >= 1.0 or (confidence is not None and not sparse_is_smaller(round(fraction * f * f), f * f, c)):
        return Message(kind="features", payload=payload, extras=extras, channel_compression=channel_compression,
                       **stamp)
    if confidence is None:
        raise ValueError("a share below 1 needs the sender's confidence map to rank its cells")
    cells = select_cells(confidence, fraction)
    return Message(kind="sparse", payload=gather(payload, cells), extras={"cells": cells, **extras},
                   channel_compression=channel_compression, **stamp)


def dense_payload(msg: Message, shape: tuple[int, int, int]) -> np.ndarray:
    """A received "features" or "sparse" message as a full [C', F, F] map (float16, zeros where unsent)."""
    if msg.kind == "sparse":
        return scatter(msg.payload, msg.extras["cells"], shape).astype(np.float16)
    return msg.payload


def cells_sent(msg: Message, cells: int) -> int:
    """How many of the `cells` feature cells the message carries."""
    return int(msg.payload.shape[0]) if msg.kind == "sparse" else cells
