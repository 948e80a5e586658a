"""Recorded runs (output.record_messages): what one ego received, frame by frame, for `v2vsim evaluate`.

Format "v2vsim.messages" version 1, a folder `messages/` beside the ego's metrics.json:

- header.json: {"format": "v2vsim.messages", "version": 1, "run_id", "run_instance" (what signatures under a shared
  comm.auth.key_file are bound to; "" before issue 45), "ego", "cavs", "frames_requested",
  "frames" (frames recorded), "chunk_frames", "chunks" (file names, in frame order), "kinds" (the V2V kinds the ego
  collected: features, points, outputs), "side" (side kinds: vis, scan, own), "scenario": {"source", "overrides",
  "resolved" (every scenario key, dotted, as JSON values: what `evaluate` compares sender-side keys against)},
  "lost_agents", "control_rejections" ([[kind, reason, n]]), "status"}. Written when recording starts and
  again at every new chunk (status "running"), then when the run ends; a run killed mid-way (SIGKILL, power)
  leaves status "running" and its chunks up to the last whole frame, which `evaluate` replays, saying so. A
  degraded run (agents lost: v2vsim.evaluation.status) went through every frame: its recording is whole.
- scenario.yaml: the scenario file the run read (a copy; evaluate reads it where the original is gone).
- files/: copies of the files the scenario names (traffic.net, traffic.buildings: SCENARIO_FILES), listed with
  their sha256 in the header's "scenario" "files" {key: {"name", "sha256"}} (recordings from before lack both).
- static.bin: the static map bytes the driver served (v2vsim.world.serialize).
- chunk_NNNNNN.bin: frames [N*chunk_frames, (N+1)*chunk_frames): b"V2VM" + u16 version, then one block per
  frame: u32 frame, u32 length, then that many bytes of zlib (level 1) over the frame's records, each u8 kind
  length, kind (ASCII), u16 sender length, sender (UTF-8: the zenoh key's sender), u32 data length, data. In order:
  one "world" record (sender "main"), then every message that the ego's collect() took for the frame, in the
  order it took them (per kind: features, points, outputs, vis, scan, own), then at most one "rejected" record
  (JSON {kind: {reason: n}}: rejections decided on arrival). The data are exactly the bytes that came off the
  wire (encoded messages: float16 features or sparse maps, points, outputs), so nothing is lost; zlib makes a
  frame of dense maps about 6x smaller. Blocks are compressed and written on a thread of their own.
"""

from __future__ import annotations

import dataclasses
import json
import queue
import shutil
import struct
import sys
import threading
import zlib
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from models.zoo import sha256  # the zoo's chunked file digest
from v2vsim.evaluation.status import finished

FORMAT = "v2vsim.messages"
VERSION = 1
CHUNK_FRAMES = 50
MAGIC = b"V2VM"
_BLOCK = struct.Struct("<II")  # frame, compressed length


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


# What acts only at the receiver: a key equal to one of these, or under one (dotted prefix). `v2vsim evaluate`
# replays a recording with other values of these keys (agents.evaluate); any other key changed what the CAVs sent.
RECEIVER_SIDE = (
    "name", "duration_s", "comm.range_m", "comm.latency_ms", "comm.drop", "comm.bandwidth_mbps", "comm.max_age_ms",
    "comm.fusion_deadline_ms", "comm.compensation", "comm.pose_noise", "comm.channel", "comm.medium",
    "perception.methods", "evaluation", "output", "transport.pipeline", "defence",
    "transport.mode", "transport.connect", "transport.listen",  # how the processes met: no bus in a replay
)


def receiver_side(key: str) -> bool:
    return any(key == r or key.startswith(r + ".") for r in RECEIVER_SIDE)


# Scenario keys naming files the run read, copied into the recording's files/ with their sha256: where the recorded
# paths are gone (a recording moved to another machine), evaluate loads the copies, and a path that differs from
# the recorded one counts as the same key when the file's content is the same. Never comm.auth.key_file (a secret).
SCENARIO_FILES = ("traffic.net", "traffic.buildings")


class MessageTape:
    """Writes a recording while the ego runs (lockstep: collect() is deterministic per frame)."""

    def __init__(self, folder: Path, sc: Any, *, run_id: str, run_instance: str, ego: str, cavs: list[str],
                 frames: int, kinds: list[str], side: list[str], static: bytes) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        for old in folder.glob("chunk_*.bin"):
            old.unlink()
        (folder / "static.bin").write_bytes(static)
        try:
            shutil.copyfile(sc.source, folder / "scenario.yaml")
        except OSError:
            pass
        resolved = resolved_keys(sc)
        files = {}
        for key in SCENARIO_FILES:  # the road network and buildings, so that a moved recording still replays
            if resolved.get(key):
                src = Path(resolved[key])
                try:
                    (folder / "files").mkdir(exist_ok=True)
                    shutil.copyfile(src, folder / "files" / src.name)
                    files[key] = {"name": src.name, "sha256": sha256(src)}
                except OSError:
                    pass
        self.header: dict[str, Any] = {
            "format": FORMAT, "version": VERSION, "run_id": run_id, "run_instance": run_instance, "ego": ego,
            "cavs": list(cavs),
            "frames_requested": frames, "frames": 0, "chunk_frames": CHUNK_FRAMES, "chunks": [],
            "kinds": list(kinds), "side": list(side),
            "scenario": {"source": sc.source, "overrides": list(sc.overrides), "resolved": resolved,
                         "files": files},
            "lost_agents": {}, "control_rejections": [], "status": "running"}
        self._file: Any = None
        self._chunk = -1
        self._frame: int | None = None
        self._records: list[bytes] = []
        self._error: Exception | None = None
        self._queue: queue.Queue = queue.Queue(maxsize=8)
        self._thread = threading.Thread(target=self._writer, name="message-tape", daemon=True)
        self._write_header()
        self._thread.start()

    def _write_header(self) -> None:
        """header.json, replaced atomically: a reader never sees half of it, and a killed run leaves one."""
        tmp = self.folder / "header.json.tmp"
        tmp.write_text(json.dumps(dict(self.header), indent=1) + "\n")
        tmp.replace(self.folder / "header.json")

    def _record(self, kind: str, sender: str, data: bytes) -> None:
        k, s = kind.encode("ascii"), sender.encode("utf-8")
        self._records += [struct.pack("<B", len(k)) + k + struct.pack("<H", len(s)) + s + struct.pack("<I", len(data)),
                          data]

    def _submit(self) -> None:
        if self._frame is not None:
            self._queue.put((self._frame, self._records))
        self._frame, self._records = None, []

    def _writer(self) -> None:
        while (item := self._queue.get()) is not None:
            frame, records = item
            try:
                block = zlib.compress(b"".join(records), 1)
                chunk = frame // CHUNK_FRAMES
                if chunk != self._chunk:
                    if self._file is not None:
                        self._file.close()
                    name = f"chunk_{chunk:06d}.bin"
                    self._file = open(self.folder / name, "ab")
                    if self._file.tell() == 0:
                        self._file.write(MAGIC + struct.pack("<H", VERSION))
                    if name not in self.header["chunks"]:
                        self.header["chunks"] = [*self.header["chunks"], name]
                        self._write_header()
                    self._chunk = chunk
                self._file.write(_BLOCK.pack(frame, len(block)) + block)
            except Exception as e:  # noqa: BLE001 - said in close(): a run never dies of its recording
                self._error = self._error or e

    def world(self, k: int, data: bytes) -> None:
        self._submit()
        self._frame = k
        self._record("world", "main", data)

    def collected(self, k: int, raw: dict[str, list[tuple[str, bytes]]], early: Counter) -> None:
        """What collect() took for frame k (Mailbox.on_collect)."""
        for kind, table in raw.items():
            for sender, data in table:
                self._record(kind, sender, data)
        if early:
            table: dict[str, dict[str, int]] = {}
            for (kind, reason), n in early.items():
                table.setdefault(kind, {})[reason] = n
            self._record("rejected", "", json.dumps(table).encode())
        self.header["frames"] = k + 1
        self._submit()

    def close(self, *, status: str, lost: dict[str, int], control: dict[tuple[str, str], int]) -> None:
        self._submit()
        self._queue.put(None)
        self._thread.join()
        if self._file is not None:
            self._file.close()
            self._file = None
        if self._error is not None:
            print(f"v2vsim-ego: the message recording is incomplete: {type(self._error).__name__}: {self._error}",
                  file=sys.stderr)
            self.header["error"] = str(self._error)
        self.header.update(status=status, lost_agents=dict(lost),
                           control_rejections=[[k, r, n] for (k, r), n in sorted(control.items())])
        self._write_header()


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

    @property
    def complete(self) -> bool:
        """Whether the recorded run went through every frame: complete, or degraded (agents lost, which its
        replay loses again from the same frames), so its header lists every chunk."""
        return finished(self.header.get("status"))

    def frames(self) -> Iterator[tuple[int, RecordedFrame]]:
        """Every recorded frame in order. A run that never ended (status "running": killed) yields its frames up
        to the last whole one: its chunk files on disk, the last one possibly cut mid-block."""
        names = self.header["chunks"] if self.complete else sorted(p.name for p in self.folder.glob("chunk_*.bin"))
        for name in names:
            yield from self._chunk(self.folder / name, cut_ok=not self.complete)

    def _chunk(self, path: Path, cut_ok: bool = False) -> Iterator[tuple[int, RecordedFrame]]:
        data = path.read_bytes()
        if data[:4] != MAGIC or len(data) < 6 or struct.unpack_from("<H", data, 4)[0] != VERSION:
            if cut_ok and len(data) < 6:
                return
            raise ValueError(f"{path}: not a {FORMAT} version {VERSION} chunk")
        at = 6
        while at < len(data):
            if at + _BLOCK.size > len(data) and cut_ok:
                return
            frame, n = _BLOCK.unpack_from(data, at)
            at += _BLOCK.size
            if at + n > len(data):
                if cut_ok:
                    return
                raise ValueError(f"{path}: truncated block of frame {frame}")
            yield frame, _frame(zlib.decompress(data[at:at + n]), path, frame)
            at += n


def _frame(body: bytes, path: Path, frame: int) -> RecordedFrame:
    out = RecordedFrame(b"", {}, Counter())
    at = 0
    while at < len(body):
        (kl,) = struct.unpack_from("<B", body, at)
        kind = body[at + 1:at + 1 + kl].decode("ascii")
        at += 1 + kl
        (sl,) = struct.unpack_from("<H", body, at)
        sender = body[at + 2:at + 2 + sl].decode("utf-8")
        at += 2 + sl
        (n,) = struct.unpack_from("<I", body, at)
        at += 4
        data = body[at:at + n]
        if len(data) != n:
            raise ValueError(f"{path}: frame {frame}: truncated {kind} record")
        at += n
        if kind == "world":
            out.world = data
        elif kind == "rejected":
            for k, reasons in json.loads(data).items():
                for reason, count in reasons.items():
                    out.rejected[(k, reason)] += count
        else:
            out.raw.setdefault(kind, []).append((sender, data))
    return out
