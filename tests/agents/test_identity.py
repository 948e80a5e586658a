"""Issue 34 items 1-2: per-process identity (comm.auth.identity per_process) and liveliness that cannot be
faked or left dangling. The codec and envelope tests are pure; the Bus tests run in-process on loopback;
the run tests start `v2vsim run` through a zenoh router, the way an attacker on the same host joins."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import agents.bus as agent_bus
from agents.bus import Bus
from v2vsim.comm import control
from v2vsim.comm import transport as T
from v2vsim.comm.codec import Message, RejectedMessage, check_arrival, decode, encode
from v2vsim.comm.control import ControlPolicy, ReplayGuard, open_sealed, seal
from v2vsim.comm.identity import IdentityError, issue, parse_identity, shared_run_key, write_identity_file

from .conftest import Sessions, client_session
from .test_hostile import _matched, _wait
from .test_run import REPO, SCENARIO, Run, _metrics

RUN = "identity-bus"
NAMES = ["driver.main", "cav.cav0", "cav.cav1", "ego.cav0"]
POLICY = ControlPolicy.for_run(["cav0", "cav1"], ["cav0"])


def _features(sender: str, frame: int = 3) -> Message:
    return Message(kind="features", run_id=RUN, sender_id=sender, frame=frame, capture_time=frame / 10,
                   sender_pose=(1.0, 2.0, 0.0, 0.5), payload=np.ones((4, 2, 2), np.float16))


# ---- the codec and the control envelope ---------------------------------------------------------


def test_a_process_signs_only_as_itself() -> None:
    ids = issue(RUN, NAMES)
    ego = ids["ego.cav0"]
    data = encode(_features("cav1"), ids["cav.cav1"])
    assert decode(data, key=ego).sender_id == "cav1" and check_arrival(data, key=ego) == (3, "cav1")
    with pytest.raises(ValueError, match="cannot sign"):  # the library refuses outright ...
        encode(_features("cav0"), ids["cav.cav1"])
    # ... and bytes made by hand are caught: cav1's signature on a message that names cav0
    forged = bytearray(encode(_features("cav1"), ids["cav.cav1"]))
    i = forged.index(b"cav1")
    forged[i:i + 4] = b"cav0"
    with pytest.raises(RejectedMessage, match="bad_signature"):
        decode(bytes(forged), key=ego)
    # a shared-key message, or none, is not a process signature; another run's keys do not verify
    with pytest.raises(RejectedMessage, match="unsigned"):
        check_arrival(encode(_features("cav1"), b"shared secret"), key=ego)
    with pytest.raises(RejectedMessage, match="bad_signature"):
        check_arrival(encode(_features("cav1"), issue(RUN, NAMES)["cav.cav1"]), key=ego)

    # control: cav1 cannot seal as the driver; a hand-made envelope naming the driver fails verification
    with pytest.raises(ValueError, match="cannot sign as driver.main"):
        seal(ids["cav.cav1"], RUN, "done", "driver.main", 10**9, b"{}")
    own = seal(ids["cav.cav1"], RUN, "done", "cav.cav1", 10**9, b"{}")
    with pytest.raises(RejectedMessage, match="unknown_sender"):  # signed fine, but a CAV may not send done
        open_sealed(ego, RUN, "done", "cav1", own, POLICY)
    # the issue's attack by hand: an envelope naming the driver, sequence 1e9, signed with cav1's key
    body = b"{}"
    name = b"driver.main"
    as_driver = (control._HEAD.pack(control.CTRL_MAGIC, control.CTRL_VERSION_IDENTITY, 10**9, len(name)) + name
                 + body + ids["cav.cav1"].sign(control._signed_bytes(RUN, "done", "driver.main", 10**9, body)))
    with pytest.raises(RejectedMessage, match="bad_signature"):
        open_sealed(ego, RUN, "done", "main", as_driver, POLICY)
    real = seal(ids["driver.main"], RUN, "done", "driver.main", 0, b"{}")
    assert open_sealed(ego, RUN, "done", "main", real, POLICY).sender == "driver.main"
    # a shared-key (version 1) envelope is refused under identities, and the other way round
    with pytest.raises(RejectedMessage, match="bad_version"):
        open_sealed(ego, RUN, "done", "main", seal(b"k", RUN, "done", "driver.main", 0, b"{}"), POLICY)
    with pytest.raises(RejectedMessage, match="bad_version"):
        open_sealed(b"k", RUN, "done", "main", real, POLICY)


def test_a_forged_sequence_number_cannot_silence_the_real_sender() -> None:
    """Issue 34 item 1: a `done` with sequence number 1e9 (signed by a shared-key holder) poisoned ReplayGuard
    and the driver's real done was then 'replayed'. A jump beyond MAX_SEQ_STEP is refused instead."""
    key = b"shared"
    guard = ReplayGuard()
    guard.check("done", open_sealed(key, RUN, "done", "main", seal(key, RUN, "done", "driver.main", 0, b"{}")))
    with pytest.raises(RejectedMessage, match="out_of_window"):
        guard.check("done", open_sealed(key, RUN, "done", "main",
                                        seal(key, RUN, "done", "driver.main", 10**9, b"{}")))
    guard.check("done", open_sealed(key, RUN, "done", "main", seal(key, RUN, "done", "driver.main", 1, b"{}")))


def test_identity_documents_say_what_is_wrong(tmp_path: Path) -> None:
    ids = issue(RUN, NAMES)
    path = tmp_path / "id" / "cav.cav1.json"
    write_identity_file(path, ids["cav.cav1"])
    assert os.stat(path).st_mode & 0o777 == 0o600
    back = parse_identity(path.read_text(), str(path), run_id=RUN, name="cav.cav1")
    assert back.verify("cav.cav1", b"x", ids["cav.cav1"].sign(b"x"))
    for text, run, name, want in [("{", RUN, "cav.cav1", "not an identity document"),
                                  (path.read_text(), "other", "cav.cav1", "issued for run 'identity-bus'"),
                                  (path.read_text(), RUN, "cav.cav0", "issued to 'cav.cav1'")]:
        with pytest.raises(IdentityError, match=want):
            parse_identity(text, "F", run_id=run, name=name)
    doc = json.loads(path.read_text())
    doc["trust"]["cav.cav1"] = doc["trust"]["cav.cav0"]  # someone else's public key listed as its own
    with pytest.raises(IdentityError, match="does not carry this process's public key"):
        parse_identity(json.dumps(doc), "F", run_id=RUN, name="cav.cav1")


# ---- the Bus: liveliness under identities --------------------------------------------------------


def test_a_token_without_a_signed_hello_is_nobody(sessions: Sessions, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 34 item 2: a fake ego token made the driver start early; one raised and withdrawn made it stop;
    one held on a dead CAV's key hid its death. Under identities presence needs a signed hello, and a
    process whose hellos stop is gone within SILENCE_S whatever tokens say."""
    monkeypatch.setattr(agent_bus, "SILENCE_S", 1.0)
    monkeypatch.setattr(agent_bus, "HEARTBEAT_S", 0.2)
    a, b, c = sessions
    ids = issue(RUN, NAMES)
    driver = Bus(a, RUN, "driver.main", key=ids["driver.main"], policy=POLICY)
    lost: list[str] = []
    driver.on_lost(lost.append)
    fake = c.liveliness().declare_token(f"v2vsim/{RUN}/alive/ego.cav0")  # the attacker's
    time.sleep(0.5)
    assert not driver.is_alive("ego.cav0") and not driver.was_alive("ego.cav0")
    with pytest.raises(TimeoutError, match="ego.cav0"):
        driver.wait_alive(["ego.cav0"], 0.5)
    fake.undeclare()  # withdrawn: nobody was there, so nobody is lost
    time.sleep(0.3)
    assert lost == [] and not driver.was_alive("ego.cav0")
    # the real ego joins: token and signed hello
    ego = Bus(b, RUN, "ego.cav0", key=ids["ego.cav0"], policy=POLICY)
    ego.ready()
    driver.wait_alive(["ego.cav0"], 10)
    assert driver.is_alive("ego.cav0")
    # the attacker holds a token on the ego's key; the ego stops saying hello (as if SIGKILLed but for the token)
    held = c.liveliness().declare_token(f"v2vsim/{RUN}/alive/ego.cav0")
    ego._closing.set()
    t0 = time.monotonic()
    assert _wait(lambda: lost == ["ego.cav0"], 5), lost
    assert time.monotonic() - t0 < 3 and not driver.is_alive("ego.cav0")
    held.undeclare()
    time.sleep(0.3)
    assert lost == ["ego.cav0"]  # counted once
    # a hello signed by someone else, published under the ego's key, is refused
    forged = seal(ids["cav.cav1"], RUN, "hello", "cav.cav1", 0, b"{}")
    _matched(c, f"v2vsim/{RUN}/hello/cav0").put(forged)  # cav1's hello published under the ego's key
    assert _wait(lambda: driver.control_rejections().get(("hello", "unknown_sender"), 0) >= 1)
    assert not driver.is_alive("ego.cav0")
    driver._closing.set()  # stop the Buses' threads; the fixture closes the sessions


# ---- end to end: `v2vsim run` through a router, an attacker beside it ------------------------------


def test_identities_stop_impersonation_and_dangling_tokens(tmp_path: Path, router: str) -> None:
    """The issue's attacks on a per_process run, by a holder of one CAV's credentials (cav1 runs as a remote
    agent, so its identity file exists): a `done` signed as the driver with sequence 1e9, a `done` in its own
    name, fake ego tokens raised and withdrawn before the ego joined, and a token held on cav1's key after
    cav1 is SIGKILLed. The run must finish every frame, count the forgeries, and notice cav1's death within
    SILENCE_S rather than the ego's 60 s hang timeout."""
    run_id, frames = "ident1", 30
    out = tmp_path / "run"
    sets = ["cavs.count=2", "comm.auth.identity=per_process", "transport.mode=client",
            f"transport.connect=[{router}]", "comm.range_m=1000", "output.rerun=false"]
    with client_session(router) as session:
        fake = session.liveliness().declare_token(f"v2vsim/{run_id}/alive/ego.cav0")
        run = Run("--frames", str(frames), "--out", str(out), "--run-id", run_id, "--remote-cavs", "cav1",
                  "--methods", "none,cobevt", *[x for s in sets for x in ("--set", s)])
        fake.undeclare()  # withdrawn before the ego joined: under token-only liveliness the driver gave up here
        fake = session.liveliness().declare_token(f"v2vsim/{run_id}/alive/ego.cav0")
        ident = out / "identity" / "cav.cav1.json"
        assert _wait(ident.is_file, 60), "".join(run.log)
        agent = subprocess.Popen([sys.executable, "-m", "v2vsim.cli", "agent", SCENARIO, "--cav", "cav1", "--run-id",
                                  run_id, "--cavs", "cav0,cav1", "--egos", "cav0", "--frames", str(frames),
                                  "--identity", str(ident), *[x for s in sets for x in ("--set", s)]],
                                 stderr=subprocess.DEVNULL, cwd=REPO)
        try:
            stolen = parse_identity(ident.read_text(), str(ident), run_id=run_id, name="cav.cav1")
            held = session.liveliness().declare_token(f"v2vsim/{run_id}/alive/cav.cav1")
            run.wait_frames(5)
            name, body = b"driver.main", json.dumps({"frames": 6}).encode()
            as_driver = (control._HEAD.pack(control.CTRL_MAGIC, control.CTRL_VERSION_IDENTITY, 10**9, len(name))
                         + name + body + stolen.sign(control._signed_bytes(run_id, "done", "driver.main", 10**9,
                                                                           body)))
            _matched(session, f"v2vsim/{run_id}/done/main").put(as_driver)
            _matched(session, f"v2vsim/{run_id}/done/cav1").put(seal(stolen, run_id, "done", "cav.cav1", 0, body))
            run.wait_frames(10)
            killed = time.monotonic()
            agent.send_signal(signal.SIGKILL)
            run.wait_for("CAV cav1 is gone", timeout=60)
            noticed = time.monotonic() - killed
            assert run.finish() == 0, "".join(run.log)
            held.undeclare()
            fake.undeclare()
        finally:
            agent.kill()
            agent.wait()
    m = _metrics(out)
    assert m["frames"] == frames and m["status"] == f"degraded: cav1 lost from frame {m['lost_agents']['cav1']}", m
    assert set(m["lost_agents"]) == {"cav1"}
    print(f"cav1's death noticed {noticed:.1f} s after SIGKILL")
    assert noticed < agent_bus.SILENCE_S + 5, noticed  # the ego's hang timeout was 60 s
    control_rejected = m["comm"]["by_kind"]["control"]["rejected_reasons"]
    assert control_rejected.get("bad_signature", 0) >= 1 and control_rejected.get("unknown_sender", 0) >= 1


def test_without_auth_a_fake_ego_token_no_longer_hangs_the_run(tmp_path: Path, router: str) -> None:
    """Issue 34 item 2 without a key: a fake ego token let the driver send frame 0 before the real ego
    listened, and both then waited forever. The driver now sends the worlds an ego has not acked again."""
    run_id, frames = "faketoken1", 8
    out = tmp_path / "run"
    with client_session(router) as session:
        fake = session.liveliness().declare_token(f"v2vsim/{run_id}/alive/ego.cav0")
        run = Run("--frames", str(frames), "--out", str(out), "--run-id", run_id, "--methods", "none",
                  "--set", "cavs.count=2", "--set", "transport.mode=client", "--set",
                  f"transport.connect=[{router}]", "--set", "output.rerun=false", "--set", "comm.auth.identity=off",
                  "--set", "transport.lost_after_s=10")  # (the default 60 s wait made this test the suite's longest)
        assert run.finish(timeout=240) == 0, "".join(run.log)
        fake.undeclare()
    m = _metrics(out)
    # unsigned, the token can cost the CAVs' first messages (sent before the real ego listened): then they are
    # lost after the ego's 60 s wait, and the run says so (issue 45) instead of "complete". Whether it happens
    # depends on who starts first; either way the status tells the truth. The default, signed run shrugs the
    # token off (below).
    assert m["frames"] == frames and m["trust"] == "off"
    assert (m["status"] == "complete" and m["lost_agents"] == {}) or (
        m["status"].startswith("degraded: ") and m["lost_agents"]), (m["status"], m["lost_agents"])


def test_replays_and_near_future_copies_are_not_counted_as_fused_bytes(tmp_path: Path, router: str) -> None:
    """Issue 34 item 4, by a holder of the shared run key: cav1's genuine signed features of frames 0-10
    played back later, and 500 signed copies claiming frames k+2..k+11, raised CoBEVT's bytes per frame
    5 % and 5x. Now they are refused on arrival (out of the window, replayed, or a second message for a
    slot), counted apart, and bytes_per_frame stays at most one message per neighbour and frame."""
    key_file = tmp_path / "run.key"
    key_file.write_text("flood run key\n")
    run_id, frames = "replay1", 40
    out = tmp_path / "run"
    run = Run("--frames", str(frames), "--out", str(out), "--run-id", run_id, "--methods", "none,cobevt",
              "--set", "cavs.count=2", "--set", "transport.mode=client", "--set", f"transport.connect=[{router}]",
              "--set", f"comm.auth.key_file={key_file}", "--set", "comm.range_m=1000", "--set", "output.rerun=false")
    key = shared_run_key(b"flood run key", run_id, run.instance())  # the key file's holder signs for this run
    genuine: dict[int, bytes] = {}
    with client_session(router) as session:
        sub = T.Subscriber(session, f"v2vsim/{run_id}/features/cav1")
        deadline = time.monotonic() + 240
        while len(genuine) < 12 and time.monotonic() < deadline:
            got = sub.get(timeout=1)
            if got is not None:
                genuine.setdefault(decode(got.data, key=key).frame, got.data)
        assert set(range(12)) <= set(genuine), ("".join(run.log), sorted(genuine))
        size = len(genuine[0])
        pub = _matched(session, f"v2vsim/{run_id}/features/cav1")
        for f in range(11):  # frames 0-10 played back at frame 11 or later
            pub.put(genuine[f])
        k = max(genuine)
        for i in range(500):  # signed copies of a real message claiming the next frames
            msg = decode(genuine[k], key=key)
            f = k + 2 + i % 10
            pub.put(encode(Message(kind=msg.kind, run_id=run_id, sender_id="cav1", frame=f, capture_time=f / 10,
                                   sender_pose=msg.sender_pose, payload=msg.payload,
                                   channel_compression=msg.channel_compression), key))
        assert run.finish() == 0, "".join(run.log)
    m = _metrics(out)
    assert m["frames"] == frames and m["status"] == "complete", m["status"]
    reasons = m["comm"]["rejected_reasons"]
    assert reasons.get("out_of_window", 0) + reasons.get("replayed", 0) >= 11, reasons  # the playback
    assert sum(reasons.get(r, 0) for r in ("out_of_window", "replayed", "duplicate")) >= 11 + 500 - 10, reasons
    assert m["methods"]["cobevt"]["bytes_per_frame"] <= size * 1.01, m["methods"]["cobevt"]  # one neighbour


# ---- trust by default (issue 45) ----------------------------------------------------------------


def _scores(m: dict) -> dict:
    """What must not depend on the transport or on wall-clock timing: every method's scores, the frames."""
    return {"frames": m["frames"], "methods": {name: {k: v for k, v in r.items() if k != "fusion_ms"}
                                               for name, r in m["methods"].items()}}


def test_a_default_run_shrugs_off_a_fake_ego_token(tmp_path: Path, router: str) -> None:
    """Issue 45 case 1 on a run started with no trust flags: under the default per-process identities a zenoh
    token proves nothing (presence is the signed hello), so the driver waits for the real ego. Every frame,
    no CAV lost, the scores of a clean run of the same seed."""
    run_id, frames = "faketoken2", 8
    common = ["--frames", str(frames), "--run-id", run_id, "--methods", "none,cobevt", "--set", "cavs.count=2",
              "--set", "comm.range_m=300", "--set", "output.rerun=false"]  # the run id's length is in the bytes
    clean = Run(*common, "--out", str(tmp_path / "clean"))
    assert clean.finish() == 0, "".join(clean.log)
    with client_session(router) as session:
        fake = session.liveliness().declare_token(f"v2vsim/{run_id}/alive/ego.cav0")
        run = Run(*common, "--out", str(tmp_path / "run"), "--set", "transport.mode=client",
                  "--set", f"transport.connect=[{router}]")
        assert run.finish(timeout=240) == 0, "".join(run.log)
        fake.undeclare()
    m = _metrics(tmp_path / "run")
    assert m["trust"] == "per_process" and m["status"] == "complete" and m["lost_agents"] == {}, m["status"]
    assert _scores(m) == _scores(_metrics(tmp_path / "clean"))
    assert "warning" not in "".join(run.log)


def test_an_earlier_run_captured_under_the_same_key_and_run_id_is_refused(tmp_path: Path, router: str) -> None:
    """Issue 45 case 4: under a shared key (comm.auth.key_file), everything an attacker captured from an earlier
    run with the same key file and --run-id (features, outputs, acks, hellos, the driver's done) is played into a
    new run from its start. Signatures are bound to the run instance, so all of it is refused as bad_signature:
    the new run fuses only its own messages and scores what the earlier, clean run scored."""
    key_file = tmp_path / "run.key"
    key_file.write_text("shared run key\n")
    run_id, frames = "crossrun1", 8
    common = ["--frames", str(frames), "--run-id", run_id, "--methods", "none,late,cobevt", "--set", "cavs.count=2",
              "--set", "comm.range_m=300", "--set", "output.rerun=false", "--set", "transport.mode=client",
              "--set", f"transport.connect=[{router}]", "--set", f"comm.auth.key_file={key_file}"]
    captured: list[tuple[str, bytes]] = []
    with client_session(router) as session:
        sub = T.Subscriber(session, f"v2vsim/{run_id}/**")
        first = Run(*common, "--out", str(tmp_path / "first"))
        assert first.finish() == 0, "".join(first.log)
        while (got := sub.get(timeout=1)) is not None:
            captured.append((got.key, got.data))
        kinds = {key.split("/")[2] for key, _ in captured}
        assert {"features", "outputs", "ack", "done", "hello"} <= kinds, kinds
        second = Run(*common, "--out", str(tmp_path / "second"))
        pubs: dict[str, T.Publisher] = {}
        while second.proc.poll() is None:  # the whole capture, again and again, for as long as the run lasts
            for key, data in captured:
                if key not in pubs:
                    pubs[key] = T.Publisher(session, key)
                pubs[key].put(data)
            time.sleep(0.05)
        assert second.finish() == 0, "".join(second.log)
    m = _metrics(tmp_path / "second")
    assert m["trust"] == "shared_key" and m["status"] == "complete" and m["lost_agents"] == {}, m["status"]
    assert m["comm"]["rejected_reasons"].get("bad_signature", 0) >= frames, m["comm"]["rejected_reasons"]
    assert m["comm"]["by_kind"]["control"]["rejected_reasons"].get("bad_signature", 0) > 0
    assert _scores(m) == _scores(_metrics(tmp_path / "first"))
