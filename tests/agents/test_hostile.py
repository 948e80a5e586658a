"""Issue 8 items 1, 3 and 9 from the outside: hostile messages on a run's bus must neither crash nor
end it, control traffic is authenticated under comm.auth, and the ego says what happened when it
crashes or the driver dies.

The Bus tests run in-process on loopback (no models); the two end-to-end tests run `v2vsim run`
through a zenoh router, the way a process on another host (or an attacker) joins a run.
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import zenoh

from agents.args import AgentArgs
from agents.bus import Bus
from v2vsim.comm import transport as T
from v2vsim.comm.codec import Message, decode, encode
from v2vsim.comm.control import ControlPolicy, open_sealed, seal
from v2vsim.comm.identity import shared_run_key
from v2vsim.config import load_scenario

from .conftest import Sessions, client_session
from .test_run import SCENARIO, Run, _metrics

RUN = "hostile-bus"
KEY = b"a shared secret"
POLICY = ControlPolicy.for_run(["cav0", "cav1"], ["cav0"])
# ---- the Bus: control messages signed, verified, filtered, counted ------------------------------


def _wait(cond: Callable[[], object], timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return False


def _matched(session: zenoh.Session, key: str) -> T.Publisher:
    pub = T.Publisher(session, key)
    assert pub.wait_matched(10), key
    return pub


def test_bus_accepts_only_signed_control_from_the_right_process(sessions: Sessions,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    a, b, c = sessions
    ego = Bus(a, RUN, "ego.cav0", key=KEY, policy=POLICY)
    driver = Bus(b, RUN, "driver.main", key=KEY, policy=POLICY)
    done: list[tuple[str, bytes]] = []
    worlds: list[bytes] = []
    ego.subscribe("done", lambda s, p: done.append((s, p)))
    ego.subscribe("world", lambda s, p: worlds.append(p))
    captured: list[bytes] = []
    spy = c.declare_subscriber(f"v2vsim/{RUN}/world/*", lambda sample: captured.append(sample.payload.to_bytes()))
    _matched(b, f"v2vsim/{RUN}/world/main").close()  # the routes from the driver to the ego are up
    sent = []
    for i in range(20):  # until the attacker's route is up too
        sent.append(f'{{"frame": {i}}}'.encode())
        driver.put("world", sent[-1])
        if _wait(lambda: worlds and captured, 0.5):
            break
    assert worlds and captured and worlds == sent[len(sent) - len(worlds):]
    assert captured[0] != sent[-1] and open_sealed(KEY, RUN, "world", "main", captured[-1]).payload == sent[-1]

    attacks = {  # (key, bytes) -> the reason the ego's bus counts it under
        (f"v2vsim/{RUN}/done/main", b"{}"): ("done", "unsigned"),  # the 2 bytes
        (f"v2vsim/{RUN}/done/main", seal(b"guessed", RUN, "done", "driver.main", 9, b"{}")): ("done", "bad_signature"),
        (f"v2vsim/{RUN}/done/main", seal(KEY, "old-run", "done", "driver.main", 9, b"{}")): ("done", "bad_signature"),
        (f"v2vsim/{RUN}/done/cav1", seal(KEY, RUN, "done", "cav.cav1", 0, b"{}")): ("done", "unknown_sender"),
        (f"v2vsim/{RUN}/done/main", seal(KEY, RUN, "ack", "driver.main", 5, b"{}")): ("done", "bad_signature"),
        (f"v2vsim/{RUN}/world/main", captured[-1]): ("world", "replayed"),  # played back in the same run
    }
    for (key, data), _ in attacks.items():
        pub = _matched(c, key)
        pub.put(data)
        pub.close()
    want: dict[tuple[str, str], int] = {}
    for v in attacks.values():
        want[v] = want.get(v, 0) + 1
    assert _wait(lambda: ego.control_rejections() == want), ego.control_rejections()
    assert done == [] and worlds[-1] == sent[-1] and len(worlds) <= len(sent)
    driver.put("done", b'{"frames": 1}')
    assert _wait(lambda: done) and done == [("main", b'{"frames": 1}')]
    # one warning per kind, not per message
    err = capsys.readouterr().err
    assert err.count("dropped a 'done' control message") == 1 and err.count("dropped a 'world'") == 1

    # a queryable answering for the driver is not believed; the driver's signed answer is
    evil = c.declare_queryable(f"v2vsim/{RUN}/static/main", lambda q: q.reply(q.key_expr, b"evil map"))
    with pytest.raises(TimeoutError, match=re.escape(f"no answer on v2vsim/{RUN}/static/main within 1 s")):
        ego.fetch("static", "main", 1.0)
    assert ego.control_rejections().get(("static", "unsigned"), 0) >= 1
    driver.serve("static", b"the map")
    assert ego.fetch("static", "main", 10) == b"the map"
    # a process ending on its own says bye; a forged bye is dropped
    _matched(c, f"v2vsim/{RUN}/bye/main").put(json.dumps({"name": "driver.main", "code": 0}).encode())
    assert _wait(lambda: ego.control_rejections().get(("bye", "unsigned"), 0) == 1)
    assert ego.farewell("driver.main") is None
    driver.say_bye(0, "finished")
    assert _wait(lambda: ego.farewell("driver.main") is not None)
    assert ego.farewell("driver.main")["code"] == 0
    evil.undeclare()
    spy.undeclare()


def test_bus_without_auth_keeps_the_old_behaviour_but_hears_only_the_right_senders(sessions: Sessions) -> None:
    a, _b, c = sessions
    ego = Bus(a, RUN, "ego.cav0", policy=POLICY)
    done: list[tuple[str, bytes]] = []
    ego.subscribe("done", lambda s, p: done.append((s, p)))
    _matched(c, f"v2vsim/{RUN}/done/cav1").put(b"{}")
    assert _wait(lambda: ego.control_rejections() == {("done", "unknown_sender"): 1})
    _matched(c, f"v2vsim/{RUN}/done/main").put(b"{}")  # nothing to verify it with: delivered as before
    assert _wait(lambda: done) and done == [("main", b"{}")]


# ---- the ego's status ---------------------------------------------------------------------------


class FakeBus:
    """Just enough of Bus for ego_loop: serves a static map, delivers world 0 when the ego is ready."""

    authenticated = False

    def __init__(self, static: bytes, world: bytes) -> None:
        self.static, self.world = static, world
        self.subs: dict[str, list[Callable[[str, bytes], None]]] = {}

    def fetch(self, kind: str, sender: str, timeout_s: float) -> bytes:
        return self.static

    def subscribe(self, kind: str, callback: Callable[[str, bytes], None], **bounds: object) -> None:
        self.subs.setdefault(kind, []).append(callback)

    def on_lost(self, callback: Callable[[str], None]) -> None:
        pass

    def ready(self) -> None:
        for cb in self.subs["world"]:
            cb("main", self.world)

    def put(self, kind: str, data: bytes) -> int:
        return len(data)

    def was_alive(self, who: str) -> bool:
        return True

    def is_alive(self, who: str) -> bool:
        return True

    def driver_gone(self) -> bool:
        return False

    def farewell(self, who: str) -> None:
        return None

    def control_rejections(self) -> dict:
        return {}


def test_a_crashed_ego_writes_crashed_not_complete(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 8 item 9: an exception in ego_loop wrote status "complete" (the finally wrote whatever it had)."""
    import agents.ego as ego_mod
    from tests.v2vsim.sensors._worlds import car, static_map
    from v2vsim.world.serialize import static_to_bytes, world_to_bytes
    from v2vsim.world.state import WorldState

    sc = load_scenario(SCENARIO, ["output.rerun=false", "perception.methods=[none]", "transport.clock=realtime"])
    static = static_map()
    world = WorldState(0.0, 0, (car("cav0", 0.0, 0.0, cav=True),), static)
    args = AgentArgs(scenario=sc, scenario_path=SCENARIO, overrides=(), run_id="crash", listen="", peers=(),
                     cavs=("cav0",), egos=("cav0",), cav="cav0", frames=3, out=str(tmp_path))

    def boom(*a: object, **kw: object) -> None:
        raise RuntimeError("boom\nsecond line")

    monkeypatch.setattr(ego_mod, "predict_all", boom)
    with pytest.raises(RuntimeError, match="boom"):
        ego_mod.ego_loop(args, FakeBus(static_to_bytes(static), world_to_bytes(world)))  # type: ignore[arg-type]
    m = _metrics(tmp_path)
    assert m["status"] == "crashed at frame 0: RuntimeError: boom second line", m["status"]
    assert m["frames"] == 0


class DriverState(FakeBus):
    def __init__(self, gone: bool, bye: dict | None = None, authenticated: bool = False) -> None:
        super().__init__(b"", b"")
        self.gone, self.bye, self.authenticated = gone, bye, authenticated  # type: ignore[misc]

    def driver_gone(self) -> bool:
        return self.gone

    def farewell(self, who: str) -> dict | None:  # type: ignore[override]
        return self.bye if who == "driver.main" else None


def test_the_ego_stops_by_itself_when_the_driver_dies(monkeypatch: pytest.MonkeyPatch) -> None:
    """What ego_loop's wait for the next world says, for each way the driver can go away."""
    import agents.ego_mailbox as mailbox

    box = mailbox.Mailbox()
    t0 = time.monotonic()
    assert mailbox.wait_world(box, DriverState(gone=True), 0, False) == "died"  # token gone, no bye
    assert 0.9 < time.monotonic() - t0 < 3
    bye = {"name": "driver.main", "code": 143, "why": "stopped by signal 15"}
    assert mailbox.wait_world(box, DriverState(gone=True, bye=bye), 0, False) == "exit 143: stopped by signal 15"
    bye = {"name": "driver.main", "code": 130, "why": "stopped by signal 2"}  # Ctrl-C reached the driver first
    assert mailbox.wait_world(box, DriverState(gone=True, bye=bye), 0, False) == "interrupted"
    mailbox.set_done(box)
    assert mailbox.wait_world(box, DriverState(gone=False, authenticated=True), 0, False) == "done"  # verified
    assert mailbox.wait_world(box, DriverState(gone=True), 0, False) == "done"  # the driver finished and left
    # without comm.auth a done is anyone's: while the driver lives, worlds still count ...
    mailbox.put_world(box, b'{"frame": 0}')
    assert mailbox.wait_world(box, DriverState(gone=False), 0, False) == (0, b'{"frame": 0}')
    # ... and the done is believed only once the driver is gone (issue 45: an honest driver says done after the
    # ego's last ack, so one that comes while the ego waits for a world is from the future), never on a timer
    mailbox.put_world(box, b'{"frame": 1}')
    assert mailbox.wait_world(box, DriverState(gone=False), 1, False) == (1, b'{"frame": 1}')
    monkeypatch.setattr(mailbox, "HANG_TIMEOUT_S", 0.5)
    assert mailbox.wait_world(box, DriverState(gone=False), 2, False) == "no world for 0.5 s"
    assert mailbox.wait_world(box, DriverState(gone=True), 2, False) == "done"


def test_every_wait_for_the_driver_is_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 34 item 2: the ego waited for a world forever when the driver, alive, sent none (a fake token had
    started the run before the ego listened). Now the wait ends with a reason the ego writes as its status."""
    import agents.ego_mailbox as mailbox

    monkeypatch.setattr(mailbox, "HANG_TIMEOUT_S", 0.3)
    monkeypatch.setattr(mailbox, "START_TIMEOUT_S", 0.6)
    box = mailbox.Mailbox()
    t0 = time.monotonic()
    assert mailbox.wait_world(box, DriverState(gone=False), 0, False) == "no world for 0.6 s"  # frame 0
    assert mailbox.wait_world(box, DriverState(gone=False), 5, False) == "no world for 0.3 s"
    assert time.monotonic() - t0 < 3


def test_side_channels_are_bounded_and_not_counted_as_v2v() -> None:
    """vis and scan (recording) messages longer than their bound are not kept, and, not being V2V
    messages, never show up in comm.rejected; an oversized V2V message is counted."""
    import struct

    import agents.ego_mailbox as mailbox

    box = mailbox.Mailbox({"features": 100, "vis": 50, "scan": 64})
    box.put("scan", "cav1", struct.pack("<q", 3) + b"x" * 100)
    box.put("scan", "cav1", struct.pack("<q", 3) + b"x" * 10)
    box.put("vis", "cav1", b"{" * 60)
    box.put("features", "cav1", b"y" * 200)
    assert list(box.raw) == [("scan", 3)] and box.rejected == {("features", "size_mismatch"): 1}


def _feature_bytes(sender: str, frame: int, key: bytes | None = None, fill: float = 0.0) -> bytes:
    msg = Message(kind="features", run_id=RUN, sender_id=sender, frame=frame, capture_time=frame / 10,
                  sender_pose=(0.0, 0.0, 0.0, 0.0), payload=np.full((4, 2, 2), fill, np.float16))
    return encode(msg, key)


def test_the_mailbox_holds_only_what_could_be_fused() -> None:
    """Issue 34 items 3-4: messages for frames beyond the pipeline's window, forged, foreign, replayed or
    duplicated are dropped on arrival and counted by reason; what is held stays bounded under any flood."""
    import agents.ego_mailbox as mailbox
    from v2vsim.comm.codec import KindSpec
    from v2vsim.comm.wire_spec import EgoDecoder

    decoder = EgoDecoder({"features": KindSpec((4, 2, 2))}, RUN, frozenset({"cav0", "cav1"}), KEY)
    window = mailbox.Window(ahead=3, behind=6)  # pipeline 1 at 10 Hz, max_age 500 ms
    box = mailbox.Mailbox({"features": 10_000}, window=window,
                          check=lambda kind, sender, data: decoder.check_arrival(kind, data, sender))
    box.put("features", "cav1", _feature_bytes("cav1", 0, KEY))  # the genuine first frame: kept
    box.put("features", "cav1", _feature_bytes("cav1", 0, KEY))  # played back: replayed
    box.put("features", "cav1", _feature_bytes("cav1", 0, KEY, 1.0))  # another one for its slot: duplicate
    box.put("features", "cav1", _feature_bytes("cav1", 1, b"guessed"))  # forged: never takes cav1's slot
    box.put("features", "cav1", _feature_bytes("cav1", 1))  # unsigned
    box.put("features", "cav1", _feature_bytes("cav0", 1, KEY))  # cav0's message under cav1's key
    box.put("features", "cav1", _feature_bytes("cav9", 1, KEY))  # nobody of this run
    box.put("features", "cav1", b"V2VS")  # too short to be anything
    for f in range(1, 3001):  # a flood for the frames ahead: nothing fused yet, so frames up to -1 + 3 are in
        box.put("features", "cav0", _feature_bytes("cav0", f, KEY))
    assert box.pending() == 3 and sorted(box.raw) == [("features", 0), ("features", 1), ("features", 2)]
    want = {"replayed": 1, "duplicate": 1, "bad_signature": 1, "unsigned": 1, "unknown_sender": 2,
            "truncated": 1, "out_of_window": 2998}
    assert {r: n for (_, r), n in box.rejected.items()} == want
    # the window moves with the frames fused; a slot once held stays held (a later replay is refused)
    with box.cond:
        box.raw.clear()
        box.mark_collected(5)
    box.put("features", "cav0", _feature_bytes("cav0", 8, KEY))  # 5 + 3: in
    box.put("features", "cav0", _feature_bytes("cav0", 9, KEY))  # out
    box.put("features", "cav0", _feature_bytes("cav0", 2, KEY))  # fused at frame 2 already: replayed
    box.put("features", "cav1", _feature_bytes("cav1", 4, KEY))  # late but still fusable: kept
    assert sorted(box.raw) == [("features", 4), ("features", 8)]
    assert box.rejected[("features", "out_of_window")] == 2999 and box.rejected[("features", "replayed")] == 2
    with box.cond:
        box.mark_collected(20)
    box.put("features", "cav1", _feature_bytes("cav1", 13, KEY))  # older than 20 - 6: can only be stale
    assert box.rejected[("features", "out_of_window")] == 3000 and box.pending() == 2


# ---- end to end, through a router ---------------------------------------------------------------


def _next(sub: T.Subscriber, run: Run, timeout: float = 240) -> T.Received:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = sub.get(timeout=1)
        if got is not None:
            return got
        assert run.proc.poll() is None, "".join(run.log)
    raise AssertionError(f"nothing on {sub.key_expr}; stderr:\n{''.join(run.log)}")


def test_hostile_messages_neither_crash_nor_end_a_run(tmp_path: Path, router: str) -> None:
    """Issue 8 items 1 and 3 as they were found: with comm.auth on, (a) an outputs message without
    boxes, signed with the run key, killed the ego (KeyError, exit 1); (b) an unsigned `{}` on the
    done key cut the run short and it still exited 0."""
    key_file = tmp_path / "run.key"
    key_file.write_text("hostile run key\n")
    out = tmp_path / "run"
    frames = 40  # (b) happens early, (a) near the end: room between them
    run = Run("--frames", str(frames), "--out", str(out), "--run-id", "hostile1", "--set", "cavs.count=2",
              "--methods", "none,late", "--set", "transport.mode=client", "--set", f"transport.connect=[{router}]",
              "--set", f"comm.auth.key_file={key_file}", "--set", "comm.range_m=1000", "--set", "output.rerun=false")
    key = shared_run_key(b"hostile run key", "hostile1", run.instance())  # the key file's holder signs for this run
    with client_session(router) as session:
        outputs = T.Subscriber(session, "v2vsim/hostile1/outputs/cav1")
        acks = T.Subscriber(session, "v2vsim/hostile1/ack/*")
        legit = decode(_next(outputs, run).data, key=key)
        rogue_pub = _matched(session, "v2vsim/hostile1/outputs/cav1")  # its routes up before the timing matters
        # (b) the 2 bytes on the done key, and a real ack played back as done and as an ack
        ack = _next(acks, run).data
        _matched(session, "v2vsim/hostile1/done/main").put(b"{}")
        _matched(session, "v2vsim/hostile1/done/cav0").put(ack)
        _matched(session, "v2vsim/hostile1/ack/cav0").put(ack)
        # (a) cav1's outputs without boxes (zeros, so it is small), for frame `frames`: a slot no real message
        # competes for (the run ends at frames - 1), sent once the ego's window admits it (the newest ack
        # + transport.pipeline 2 + 2 >= frames). The ego must count it at decode, not crash on it.
        f = frames
        while json.loads(open_sealed(key, "hostile1", "ack", "cav0", ack).payload)["frame"] < f - 4:
            ack = _next(acks, run).data
        rogue = Message(kind="outputs", run_id="hostile1", sender_id="cav1", frame=f, capture_time=f / 10,
                        sender_pose=legit.sender_pose, payload=np.zeros_like(legit.payload), compression="zlib")
        rogue_pub.put(encode(rogue, key))
        assert run.finish() == 0, "".join(run.log)
    m = _metrics(out)
    assert m["frames"] == frames and m["status"] == "complete", m["status"]
    comm = m["comm"]
    assert comm["by_kind"]["outputs"]["rejected_reasons"] == {"missing_extra": 1}
    # the ego refused the two dones; the driver the played-back ack, which the run's metrics.json counts too (issue 52)
    assert comm["by_kind"]["control"]["rejected_reasons"] == {"unsigned": 1, "bad_signature": 1, "replayed": 1}
    assert {"missing_extra": 1, "unsigned": 1, "bad_signature": 1, "replayed": 1}.items() <= \
        comm["rejected_reasons"].items()
    log = "".join(run.log)
    assert "dropped a 'done' control message" in log and "replayed" in log  # the driver refused the old ack
