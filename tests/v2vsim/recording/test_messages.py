"""The v2vsim.messages format (output.record_messages): what a MessageTape writes reads back exactly, frame by
frame and in order, and a recording that is not one (no header, another format or version, a cut chunk) is a
one-line ValueError."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest

from v2vsim.config import load_scenario
from v2vsim.recording import messages
from v2vsim.recording.messages import MessageTape, Recording, resolved_keys


def _tape(folder: Path, frames: int) -> list[tuple[int, dict, Counter]]:
    sc = load_scenario("intersection", ["cavs.count=2"])
    tape = MessageTape(folder, sc, run_id="r1", run_instance="i1", ego="cav0", cavs=["cav0", "cav1"], frames=frames,
                       kinds=["features", "outputs"], side=["vis"], static=b"static-map")
    written = []
    for k in range(frames):
        raw = {"features": [("cav1", bytes([k]) * 1000), ("cav0", b"f0-%d" % k)], "outputs": [],
               "vis": [("cav1", json.dumps({"frame": k, "ids": ["v1"]}).encode())]}
        early = Counter({("features", "bad_signature"): 2}) if k == 3 else Counter()
        tape.world(k, b"world-%d" % k)
        tape.collected(k, raw, early)
        written.append((k, raw, early))
    tape.close(status="complete", lost={"cav1": 5}, control={("done", "bad_signature"): 1})
    return written


def test_a_tape_reads_back_exactly(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(messages, "CHUNK_FRAMES", 4)  # three chunks for 10 frames
    written = _tape(tmp_path / "messages", 10)
    rec = Recording(tmp_path)  # the run folder or messages/ itself
    assert Recording(tmp_path / "messages").header == rec.header
    h = rec.header
    assert h["format"] == "v2vsim.messages" and h["version"] == 1 and h["frames"] == 10 and h["run_id"] == "r1"
    assert h["chunks"] == ["chunk_000000.bin", "chunk_000001.bin", "chunk_000002.bin"]
    assert h["lost_agents"] == {"cav1": 5} and h["control_rejections"] == [["done", "bad_signature", 1]]
    assert h["scenario"]["resolved"]["cavs.count"] == 2
    assert rec.static == b"static-map"
    got = list(rec.frames())
    assert [k for k, _ in got] == list(range(10))
    for (k, f), (_, raw, early) in zip(got, written, strict=True):
        assert f.world == b"world-%d" % k
        assert f.raw == {kind: table for kind, table in raw.items() if table}  # order within a kind kept
        assert f.rejected == early


def test_what_is_not_a_recording_is_one_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no recording here"):
        Recording(tmp_path)
    _tape(tmp_path / "messages", 3)
    head = tmp_path / "messages" / "header.json"
    h = json.loads(head.read_text())
    head.write_text(json.dumps({**h, "version": 99}))
    with pytest.raises(ValueError, match="format version 99"):
        Recording(tmp_path)
    head.write_text(json.dumps(h))
    chunk = tmp_path / "messages" / "chunk_000000.bin"
    chunk.write_bytes(chunk.read_bytes()[:-10])
    with pytest.raises(ValueError, match="truncated"):
        list(Recording(tmp_path).frames())


def test_a_killed_run_leaves_a_header_and_its_whole_frames(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """No close(): the process died. header.json says "running" and lists the chunks it had started; the frames up
    to the last whole one read back, the cut block after them is dropped."""
    monkeypatch.setattr(messages, "CHUNK_FRAMES", 4)
    sc = load_scenario("intersection", ["cavs.count=2"])
    folder = tmp_path / "messages"
    tape = MessageTape(folder, sc, run_id="r1", run_instance="i1", ego="cav0", cavs=["cav0", "cav1"], frames=20,
                       kinds=["features"],
                       side=[], static=b"static-map")
    assert json.loads((folder / "header.json").read_text())["status"] == "running"  # written at the start
    for k in range(7):
        tape.world(k, b"world-%d" % k)
        tape.collected(k, {"features": [("cav1", bytes([k]) * 500)]}, Counter())
    tape._submit()
    tape._queue.put(None)  # let the writer finish what it has, as the OS would have flushed it; then "die"
    tape._thread.join()
    tape._file.close()
    chunk = folder / "chunk_000001.bin"
    chunk.write_bytes(chunk.read_bytes()[:-7])  # frame 6 cut mid-block
    rec = Recording(tmp_path)
    assert rec.header["status"] == "running" and not rec.complete
    assert [k for k, _ in rec.frames()] == [0, 1, 2, 3, 4, 5]
    assert not list(folder.glob("*.tmp"))


def test_resolved_keys_are_dotted_json_values() -> None:
    keys = resolved_keys(load_scenario("intersection", ["comm.drop.p=0.25"]))
    assert keys["comm.drop.p"] == 0.25 and "comm.latency_ms.jitter" in keys
    assert isinstance(keys["perception.methods"], list) and "source" not in keys and "overrides" not in keys
