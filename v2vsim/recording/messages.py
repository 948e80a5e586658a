"""Recorded runs (output.record_messages): what one ego received, frame by frame, for `v2vsim evaluate`.

Format "v2vsim.messages" version 1, a folder `messages/` beside the ego's metrics.json:

- header.json: {"format": "v2vsim.messages", "version": 1, "run_id", "ego", "cavs", "frames_requested",
  "frames" (frames recorded), "chunk_frames", "chunks" (file names, in frame order), "kinds" (the V2V kinds the ego
  collected: features, points, outputs), "side" (side kinds: vis, scan, own), "scenario": {"source", "overrides",
  "resolved" (every scenario key, dotted, as JSON values: what `evaluate` compares sender-side keys against)},
  "lost_agents", "control_rejections" ([[kind, reason, n]]), "status"}. Written when the run ends.
- scenario.yaml: the scenario file the run read (a copy; evaluate reads it where the original is gone).
- static.bin: the static map bytes the driver served (v2vsim.world.serialize).
- chunk_NNNNNN.bin: frames [N*chunk_frames, (N+1)*chunk_frames): b"V2VM" + u16 version, then records, each
  u8 kind length, kind (ASCII), u16 sender length, sender (UTF-8: the zenoh key's sender), u32 frame, u32 data
  length, data. Per frame, in order: one "world" record (sender "main"), then every message that the ego's
  collect() took for the frame, in the order it took them (per kind: features, points, outputs, vis, scan, own),
  then at most one "rejected" record (JSON {kind: {reason: n}}: rejections decided on arrival). Bytes are exactly
  what came off the wire (encoded messages: float16 features or sparse maps, points, outputs), so nothing is lost.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import struct
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

FORMAT = "v2vsim.messages"
VERSION = 1
CHUNK_FRAMES = 50
MAGIC = b"V2VM"
_REC = struct.Struct("<II")  # frame, data length


def resolved_keys(sc: Any) -> dict[str, Any]:
    """Every scenario key, dotted, with a JSON value (tuples as lists; internal fields left out)."""
    out: dict[str, Any] = {}

    def walk(obj: Any, prefix: str) -> None:
        for f in dataclasses.fields(obj):
            if f.metadata.get("internal"):
                continue
            v = getattr(obj, f.name)
            if dataclasses.is_dataclass(v):
                walk(v, f"{prefix}{f.name}.")
            else:
                out[f"{prefix}{f.name}"] = json.loads(json.dumps(v, default=str))
    walk(sc, "")
    return out


class MessageTape:
    """Writes a recording while the ego runs (lockstep: collect() is deterministic per frame)."""

    def __init__(self, folder: Path, sc: Any, *, run_id: str, ego: str, cavs: list[str], frames: int,
                 kinds: list[str], side: list[str], static: bytes) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        for old in folder.glob("chunk_*.bin"):
            old.unlink()
        (folder / "static.bin").write_bytes(static)
        try:
            shutil.copyfile(sc.source, folder / "scenario.yaml")
        except OSError:
            pass
        self.header: dict[str, Any] = {
            "format": FORMAT, "version": VERSION, "run_id": run_id, "ego": ego, "cavs": list(cavs),
            "frames_requested": frames, "frames": 0, "chunk_frames": CHUNK_FRAMES, "chunks": [],
            "kinds": list(kinds), "side": list(side),
            "scenario": {"source": sc.source, "overrides": list(sc.overrides), "resolved": resolved_keys(sc)},
            "lost_agents": {}, "control_rejections": [], "status": "running"}
        self._file: Any = None
        self._chunk = -1

    def _write(self, frame: int, kind: str, sender: str, data: bytes) -> None:
        chunk = frame // CHUNK_FRAMES
        if chunk != self._chunk:
            if self._file is not None:
                self._file.close()
            name = f"chunk_{chunk:06d}.bin"
            self._file = open(self.folder / name, "ab")
            if self._file.tell() == 0:
                self._file.write(MAGIC + struct.pack("<H", VERSION))
            if name not in self.header["chunks"]:
                self.header["chunks"].append(name)
            self._chunk = chunk
        k, s = kind.encode("ascii"), sender.encode("utf-8")
        self._file.write(struct.pack("<B", len(k)) + k + struct.pack("<H", len(s)) + s + _REC.pack(frame, len(data)))
        self._file.write(data)

    def world(self, k: int, data: bytes) -> None:
        self._write(k, "world", "main", data)

    def collected(self, k: int, raw: dict[str, list[tuple[str, bytes]]], early: Counter) -> None:
        """What collect() took for frame k (Mailbox.on_collect)."""
        for kind, table in raw.items():
            for sender, data in table:
                self._write(k, kind, sender, data)
        if early:
            table: dict[str, dict[str, int]] = {}
            for (kind, reason), n in early.items():
                table.setdefault(kind, {})[reason] = n
            self._write(k, "rejected", "", json.dumps(table).encode())
        self.header["frames"] = k + 1
        self._file.flush()

    def close(self, *, status: str, lost: dict[str, int], control: dict[tuple[str, str], int]) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
        self.header.update(status=status, lost_agents=dict(lost),
                           control_rejections=[[k, r, n] for (k, r), n in sorted(control.items())])
        (self.folder / "header.json").write_text(json.dumps(self.header, indent=1) + "\n")


@dataclasses.dataclass
class RecordedFrame:
    world: bytes
    raw: dict[str, list[tuple[str, bytes]]]
    rejected: Counter


class Recording:
    """A recording read back (header, static bytes, frames in order)."""

    def __init__(self, path: Path) -> None:
        folder = path / "messages" if (path / "messages" / "header.json").exists() else path
        head = folder / "header.json"
        if not head.exists():
            raise ValueError(f"{path}: no recording here (expected messages/header.json; record a run with "
                             "--set output.record_messages=true)")
        try:
            self.header = json.loads(head.read_text())
        except ValueError as e:
            raise ValueError(f"{head}: not valid JSON: {e}") from None
        if self.header.get("format") != FORMAT:
            raise ValueError(f"{head}: format {self.header.get('format')!r}, expected {FORMAT!r}")
        if self.header.get("version") != VERSION:
            raise ValueError(f"{head}: format version {self.header.get('version')!r}; this v2vsim reads {VERSION}")
        self.folder = folder
        self.static = (folder / "static.bin").read_bytes()

    def frames(self) -> Iterator[tuple[int, RecordedFrame]]:
        for name in self.header["chunks"]:
            yield from self._chunk(self.folder / name)

    def _chunk(self, path: Path) -> Iterator[tuple[int, RecordedFrame]]:
        data = path.read_bytes()
        if data[:4] != MAGIC or struct.unpack_from("<H", data, 4)[0] != VERSION:
            raise ValueError(f"{path}: not a v2vsim.messages version {VERSION} chunk")
        at, cur, frame = 6, None, -1
        while at < len(data):
            (kl,) = struct.unpack_from("<B", data, at)
            kind = data[at + 1:at + 1 + kl].decode("ascii")
            at += 1 + kl
            (sl,) = struct.unpack_from("<H", data, at)
            sender = data[at + 2:at + 2 + sl].decode("utf-8")
            at += 2 + sl
            f, n = _REC.unpack_from(data, at)
            at += _REC.size
            body = data[at:at + n]
            if len(body) != n:
                raise ValueError(f"{path}: truncated at byte {at}")
            at += n
            if kind == "world":
                if cur is not None:
                    yield frame, cur
                cur, frame = RecordedFrame(body, {}, Counter()), f
            elif cur is None or f != frame:
                raise ValueError(f"{path}: a {kind} record of frame {f} outside its frame")
            elif kind == "rejected":
                for k, reasons in json.loads(body).items():
                    for reason, count in reasons.items():
                        cur.rejected[(k, reason)] += count
            else:
                cur.raw.setdefault(kind, []).append((sender, body))
        if cur is not None:
            yield frame, cur
