"""The bus of a replay (`v2vsim evaluate`): a recording (v2vsim.recording.messages) played into the ego's
mailbox, one frame per ack, so that agents.ego.ego_loop runs unchanged with no driver, CAVs or zenoh.

Frame k's world and every message collect() took for frame k when recorded go into the mailbox when the ego
acks frame k-1 (frame 0: when it says ready), straight into its tables: they passed the arrival
checks (signature, run, sender, window) when they were recorded, and the decode that follows skips the
signature as it did then. Rejections decided on arrival are put back as counted. A CAV lost in the recorded
run is lost again from the same frame; the run ends as the recorded one did (its frames, then done).

Several points of one recording replayed in one process (`v2vsim evaluate --grid`, a sweep's replays) run one
ego_loop thread each over a ReplayShare: the recording is read and decompressed once, and what is a pure
function of a frame's bytes (a message's decode, the world, the ground truth, a method's prediction from the
same fusion inputs: v2vsim.perception.fuse.fusion_key) is computed by the first point that needs it and reused,
bit for bit, by the others. Every point keeps its own channel models, counts, scores and output files.
"""

from __future__ import annotations

import hashlib
import threading
from collections import Counter
from collections.abc import Callable, Hashable, Iterator
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
import torch
from torch import nn

from agents.ego_mailbox import Mailbox
from agents.lifecycle import Stop
from v2vsim.comm.message import Message, RejectedMessage
from v2vsim.comm.wire_spec import EgoDecoder
from v2vsim.perception.fuse import Prediction
from v2vsim.recording.messages import RecordedFrame, Recording

T = TypeVar("T")


@dataclass
class _Slot:
    done: threading.Event = field(default_factory=threading.Event)
    value: Any = None
    error: BaseException | None = None


class ReplayShare:
    """One recording read once for `consumers` replays running as threads of one process, and the memo of
    what they compute alike. A consumer may run at most AHEAD frames past the slowest live one, so that the
    frames and memo entries kept (everything of frames some live consumer has not finished) stay bounded."""

    AHEAD = 4

    def __init__(self, recording: Recording, consumers: int) -> None:
        self._it: Iterator[tuple[int, RecordedFrame]] = recording.frames()
        self._read: list[tuple[int, RecordedFrame]] = []  # [(k, frame)] not yet finished by every consumer
        self._base = 0  # index into the recording's frame sequence of self._read[0]
        self._ended = False
        self._at = [0] * consumers  # per consumer: the index of the frame it works on (or will take next)
        self._live = [True] * consumers
        self._memo: dict[tuple[int, Hashable], _Slot] = {}
        self._cond = threading.Condition()
        self._stopped = False
        # memo lookups by what they are for (key[0]: decode, world, ground_truth, prediction), and of those how many
        # another consumer's work answered (evaluate's last line says)
        self.lookups: Counter[str] = Counter()
        self.hits: Counter[str] = Counter()

    def take(self, consumer: int, index: int) -> tuple[int, RecordedFrame] | None:
        """The `index`-th recorded frame (0, 1, ...), or None past the last; waits while this consumer is
        AHEAD frames past the slowest. Raises Stop once stop() was called."""
        with self._cond:
            self._at[consumer] = index
            self._evict()
            while not self._stopped and index > self._slowest() + self.AHEAD:
                self._cond.wait(0.5)
            if self._stopped:
                raise Stop(0)
            while not self._ended and index - self._base >= len(self._read):
                got = next(self._it, None)
                if got is None:
                    self._ended = True
                else:
                    self._read.append(got)
            i = index - self._base
            return self._read[i] if i < len(self._read) else None

    def leave(self, consumer: int) -> None:
        """This consumer's replay ended: it no longer holds frames back."""
        with self._cond:
            self._live[consumer] = False
            self._evict()
            self._cond.notify_all()

    def stop(self) -> None:
        """Ctrl-C: every consumer stops at its next frame (ego_loop writes its results as interrupted)."""
        with self._cond:
            self._stopped = True
            self._cond.notify_all()

    def once(self, frame: int, key: Hashable, compute: Callable[[], T]) -> T:
        """compute() for (frame, key) by the first consumer that asks; the others wait for it and get the same
        object. An exception is raised in every consumer that asks. Frame -1: kept for the whole recording."""
        what = str(key[0]) if isinstance(key, tuple) else str(key)
        with self._cond:
            self.lookups[what] += 1
            slot = self._memo.get((frame, key))
            owner = slot is None
            if slot is None:
                slot = self._memo[(frame, key)] = _Slot()
            else:
                self.hits[what] += 1
        if owner:
            try:
                slot.value = compute()
            except BaseException as e:
                slot.error = e
                raise
            finally:
                slot.done.set()
            return slot.value
        slot.done.wait()
        if slot.error is not None:
            raise slot.error
        return slot.value

    def _slowest(self) -> int:
        live = [a for a, alive in zip(self._at, self._live, strict=True) if alive]
        return min(live) if live else 1 << 62

    def _evict(self) -> None:
        """Drop the frames (and their memo entries) every live consumer is done with."""
        slowest = self._slowest()
        gone = min(slowest - self._base, len(self._read))
        if gone <= 0:
            return
        finished = {k for k, _ in self._read[:gone]}
        del self._read[:gone]
        self._base += gone
        for key in [key for key in self._memo if key[0] in finished]:
            del self._memo[key]
        self._cond.notify_all()


class ReplayBus:
    authenticated = True  # a done is the recording's: believed at once

    def __init__(self, recording: Recording, frames: int, share: ReplayShare | None = None, consumer: int = 0,
                 label: str | None = None) -> None:
        self.recording = recording
        self.frames = frames
        self.share = share
        self.consumer = consumer
        self.label = label  # the progress lines' name of this replay (several in one process)
        self._it: Iterator[tuple[int, RecordedFrame]] | None = recording.frames() if share is None else None
        self._index = 0
        self._subs: dict[str, Callable[[str, bytes], None]] = {}
        self._box: Mailbox | None = None
        self._lost = {str(c): int(f) for c, f in recording.header.get("lost_agents", {}).items()}
        self._current = -1
        self._model_ids: dict[int, bytes] = {}

    def attach(self, box: Mailbox) -> None:
        self._box = box

    def once(self, key: Hashable, compute: Callable[[], T]) -> T:
        """compute(), shared with the other replays of this process for the frame being worked on (its arrays made
        read-only: read_only)."""
        if self.share is None:
            return compute()
        return self.share.once(self._current, key, lambda: read_only(compute()))

    def once_per_recording(self, key: Hashable, compute: Callable[[], T]) -> T:
        """compute(), shared with the other replays of this process for the whole recording (never dropped)."""
        return compute() if self.share is None else self.share.once(-1, key, compute)

    def decoder(self, decoder: EgoDecoder, tag: str) -> EgoDecoder:
        """`decoder` whose decodes are shared with the other replays (counting stays per replay); `tag` tells
        decoders of different wire specs apart."""
        return decoder if self.share is None else _SharedDecoder(decoder, self, tag)  # type: ignore[return-value]

    def prediction_memo(self, precision: str, cells: int) -> Callable[..., Prediction | None] | None:
        """For v2vsim.evaluation.fuse_and_score.predict_all: a method's prediction from inputs another replay
        fused already (the same model weights, precision and fusion_key) is that replay's, bit for bit."""
        if self.share is None:
            return None

        def memo(method: str, model: nn.Module, key: bytes,
                 compute: Callable[[], Prediction | None]) -> Prediction | None:
            return self.once(("prediction", method, self._model_id(model), precision, cells, key), compute)

        return memo

    def _model_id(self, model: nn.Module) -> bytes:
        """A digest of the model's class and every parameter and buffer, and the device each sits on: two replays'
        copies of one checkpoint on one device match, anything else does not (a GPU rounds otherwise than the CPU)."""
        got = self._model_ids.get(id(model))
        if got is None:
            h = hashlib.sha1(f"{type(model).__qualname__} {getattr(model, 'bev_size_m', None)} {model!r}".encode())
            for name, t in [*model.named_parameters(), *model.named_buffers()]:  # non-persistent buffers too
                h.update(name.encode())
                h.update(str(t.dtype).encode() + str(tuple(t.shape)).encode() + str(t.device).encode())
                h.update(t.detach().reshape(-1).contiguous().view(torch.uint8).cpu().numpy().tobytes())
            got = self._model_ids[id(model)] = h.digest()
        return got

    # the Bus methods ego_loop uses
    def fetch(self, kind: str, sender: str, timeout_s: float) -> bytes:
        assert kind == "static"
        return self.recording.static

    def subscribe(self, kind: str, callback: Callable[[str, bytes], None], **_bounds: object) -> None:
        self._subs[kind] = callback  # a recording's messages passed the length bounds when recorded

    def on_lost(self, callback: Callable[[str], None]) -> None:
        pass

    def ready(self) -> None:
        self._feed()

    def put(self, kind: str, data: bytes) -> int:
        if kind == "ack":
            self._feed()
        return len(data)

    def driver_gone(self) -> bool:
        return False

    def farewell(self, who: str) -> dict[str, Any] | None:
        return None

    def was_alive(self, who: str) -> bool:
        return True

    def is_alive(self, who: str) -> bool:
        cav = who.split(".", 1)[1] if who.startswith("cav.") else who
        return not (cav in self._lost and self._current >= self._lost[cav])

    def control_rejections(self) -> dict[tuple[str, str], int]:
        return {(k, r): int(n) for k, r, n in self.recording.header.get("control_rejections", [])}

    def close(self) -> None:
        """The replay ended (however): it no longer holds the other replays of its process back."""
        if self.share is not None:
            self.share.leave(self.consumer)

    def _next(self) -> tuple[int, RecordedFrame] | None:
        if self.share is None:
            assert self._it is not None
            return next(self._it, None)
        got = self.share.take(self.consumer, self._index)
        self._index += 1
        return got

    def _feed(self) -> None:
        box = self._box
        assert box is not None, "ReplayBus.attach(mailbox) before the ego starts"
        got = self._next()
        if got is None or got[0] >= self.frames:
            self._subs["done"]("main", b"")
            return
        k, frame = got
        self._current = k
        with box.cond:
            for kind, table in frame.raw.items():
                if kind not in self._subs:  # a kind this ego does not take (fewer methods): never sent to it
                    continue
                box.raw[(kind, k)].extend(table)
            box.rejected.update(frame.rejected)
            # straight in too, past the window: a realtime recording may skip more frames than it holds
            box.worlds[k] = frame.world
            box.newest_world = max(box.newest_world, k)
            box.cond.notify_all()


def read_only(value: T) -> T:
    """`value` with every numpy array in it (in dicts, tuples, lists, a Prediction) made read-only: what replays
    share, none of them may change (a write raises instead of corrupting the others' results)."""
    if isinstance(value, np.ndarray):
        value.flags.writeable = False
    elif isinstance(value, dict):
        for v in value.values():
            read_only(v)
    elif isinstance(value, (tuple, list)):
        for v in value:
            read_only(v)
    elif isinstance(value, Prediction):
        read_only(value.probs)
        read_only(value.boxes)
    return value


class _SharedDecoder:
    """An EgoDecoder whose decode of given bytes is done once for all replays of a process (it depends on the
    bytes, the sender and the recording's wire spec only); each replay still counts its own rejections."""

    def __init__(self, decoder: EgoDecoder, bus: ReplayBus, tag: str) -> None:
        self._decoder = decoder
        self._bus = bus
        self._tag = tag

    def __getattr__(self, name: str) -> Any:
        return getattr(self._decoder, name)

    def receive(self, kind: str, data: bytes, sender: str | None, stats: Any, *,
                verified: bool = False) -> Message | None:
        got = self._bus.once(("decode", self._tag, kind, sender, verified, data),
                             lambda: _decode_or_reason(self._decoder, kind, data, sender, verified))
        if isinstance(got, RejectedMessage):
            for s in stats:
                s.record_rejected(got.reason)
            return None
        return got


def _decode_or_reason(decoder: EgoDecoder, kind: str, data: bytes, sender: str | None,
                      verified: bool) -> Message | RejectedMessage:
    try:
        msg = decoder.decode(kind, data, sender, verified=verified)
    except RejectedMessage as e:
        return e
    read_only([msg.payload, *msg.extras.values()])  # shared by every replay of the process
    return msg

