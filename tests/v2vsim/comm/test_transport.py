"""zenoh transport on loopback only: config, clear errors, and a three-process exchange."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import textwrap
import time

import pytest

from v2vsim.comm import transport as T
from v2vsim.config import TransportConfig


def test_keys() -> None:
    k = T.message_key("run1", "features", "cav2")
    assert k == "v2vsim/run1/features/cav2"
    assert T.parse_key(k) == ("run1", "features", "cav2")
    assert T.subscription_key("run1", "features") == "v2vsim/run1/features/*"
    assert T.subscription_key("run1") == "v2vsim/run1/**"
    for bad in ("a/b", "*", "", "x$y", "@admin"):
        with pytest.raises(ValueError, match=re.escape(f"sender id {bad!r} cannot be a zenoh key chunk")):
            T.message_key("run1", "features", bad)
    with pytest.raises(ValueError, match=re.escape("not a v2vsim message key: 'v2vsim/run1/features'")):
        T.parse_key("v2vsim/run1/features")


def _endpoints(cfg: dict) -> list[str]:
    out = []
    for section in ("listen", "connect"):
        eps = cfg[section]["endpoints"]
        out += eps if isinstance(eps, list) else [e for v in eps.values() for e in v]
    return out


def test_config_is_loopback_and_quiet() -> None:
    port = T.free_port()
    cfg = json.loads(str(T.zenoh_config(TransportConfig(), port, peers=["tcp/127.0.0.1:1"])))
    assert cfg["mode"] == "peer"
    assert cfg["scouting"]["multicast"]["enabled"] is False
    assert cfg["scouting"]["gossip"]["enabled"] is False
    assert cfg["listen"]["endpoints"] == [f"tcp/127.0.0.1:{port}"]
    assert all(e.startswith("tcp/127.") for e in _endpoints(cfg))
    default = json.loads(str(T.zenoh_config(TransportConfig())))
    assert default["listen"]["endpoints"] == ["tcp/127.0.0.1:0"] and default["connect"]["endpoints"] == []
    with pytest.raises(T.TransportError, match=r"transport\.mode is 'client' but transport\.connect names no router"):
        T.zenoh_config(TransportConfig(mode="client"))  # a client needs a router to connect to


def test_port_in_use_is_a_one_line_error() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(T.TransportError) as ei:
            T.open_session(TransportConfig(), port)
    msg = str(ei.value)
    assert "address already in use" in msg and str(port) in msg and "\n" not in msg


@pytest.mark.parametrize("mode", ["client", "peer"])
def test_unreachable_router_is_a_one_line_error(mode: str) -> None:
    dead = f"tcp/127.0.0.1:{T.free_port()}"
    t0 = time.monotonic()
    with pytest.raises(T.TransportError) as ei:
        T.open_session(TransportConfig(mode=mode, connect=(dead,)), connect_timeout_ms=500)
    assert time.monotonic() - t0 < 5
    msg = str(ei.value)
    assert "cannot reach" in msg and dead in msg and "\n" not in msg


def test_optional_peer_that_is_not_up_yet_does_not_fail() -> None:
    """A session whose peer is not listening yet opens, and reaches that peer once it comes up."""
    port = T.free_port()
    early = T.open_session(TransportConfig(), peers=[T.loopback_endpoint(port)])
    late = None
    try:
        late = T.open_session(TransportConfig(), port)
        sub = T.Subscriber(late, T.subscription_key("r", "features"))
        pub = T.Publisher(early, T.message_key("r", "features", "cav1"))
        assert pub.wait_matched(15), "the session never reached the peer that came up after it"
        pub.put(b"hello")
        got = sub.get(timeout=10)
        assert got is not None and got.data == b"hello"
    finally:
        if late is not None:
            late.close()
        early.close()


def test_in_process_pub_sub() -> None:
    port = T.free_port()
    a = T.open_session(TransportConfig(), port)
    b = T.open_session(TransportConfig(), peers=[T.loopback_endpoint(port)])
    try:
        sub = T.Subscriber(a, T.subscription_key("r", "features"))
        pub = T.Publisher(b, T.message_key("r", "features", "cav1"))
        assert pub.wait_matched(10)
        payload = os.urandom(300_000)
        assert pub.put(payload) == len(payload)
        got = sub.get(timeout=10)
        assert got is not None and got.key == "v2vsim/r/features/cav1" and got.data == payload
    finally:
        b.close()
        a.close()


# ---- three processes -------------------------------------------------------------------------

_CHILD = textwrap.dedent("""
    import json, sys, time
    import numpy as np
    from v2vsim.comm import codec, transport as T
    from v2vsim.config import TransportConfig

    role, run_id, port, key_hex = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
    key = bytes.fromhex(key_hex)
    deadline = time.monotonic() + 12.0
    if role == "sub":
        for attempt in range(5):  # free_port can race with another process: take another one
            try:
                port = T.free_port()
                session = T.open_session(TransportConfig(), port)
                break
            except T.TransportError:
                if attempt == 4:
                    raise
        sub = T.Subscriber(session, T.subscription_key(run_id, "features"))
        print("READY", port, flush=True)
        got, rejected = {}, []
        while set(got) != {"cav1", "cav2"} and time.monotonic() < deadline:
            r = sub.get(timeout=0.2)
            if r is None:
                continue
            try:
                m = codec.decode(r.data, key=key, known_senders={"cav1", "cav2"},
                                 expected={"features": (8, 16, 16)}, run_id=run_id)
            except codec.RejectedMessage as e:
                rejected.append(e.reason)
                continue
            assert T.parse_key(r.key)[2] == m.sender_id
            got[m.sender_id] = [m.frame, float(m.payload.astype(np.float32).sum())]
        print(json.dumps({"got": got, "rejected": rejected}), flush=True)
    else:
        session = T.open_session(TransportConfig(), peers=[T.loopback_endpoint(port)])
        pub = T.Publisher(session, T.message_key(run_id, "features", role))
        if not pub.wait_matched(10.0):
            print("NO MATCH", flush=True)
            sys.exit(3)
        # an unsigned message first: the subscriber must reject it and keep going
        bad = codec.Message("features", run_id, role, 0, 0.0, (0.0, 0.0, 0.0, 0.0), np.ones((8, 16, 16)))
        pub.put(codec.encode(bad))
        for frame in range(1, 40):
            msg = codec.Message("features", run_id, role, frame, frame * 0.1, (float(frame), 0.0, 0.0, 0.0),
                                np.full((8, 16, 16), 0.5 if role == "cav1" else 0.25, np.float32))
            pub.put(codec.encode(msg, key))
            time.sleep(0.05)
            if time.monotonic() > deadline:
                break
        print("SENT", flush=True)
    session.close()
""")


def test_three_process_exchange() -> None:
    """Two publisher processes and one subscriber process, each its own zenoh peer session."""
    run_id, key = "t3p", os.urandom(16).hex()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    t0 = time.monotonic()
    sub = subprocess.Popen([sys.executable, "-c", _CHILD, "sub", run_id, "0", key],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    pubs: list[subprocess.Popen] = []
    try:
        line = sub.stdout.readline() if sub.stdout else ""
        assert line.startswith("READY "), (line, sub.stderr.read() if sub.stderr else "")
        port = int(line.split()[1])
        pubs = [subprocess.Popen([sys.executable, "-c", _CHILD, name, run_id, str(port), key],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
                for name in ("cav1", "cav2")]
        out, err = sub.communicate(timeout=20)
        result = json.loads(out.strip().splitlines()[-1])
        assert set(result["got"]) == {"cav1", "cav2"}, (result, err)
        assert result["got"]["cav1"][1] == pytest.approx(0.5 * 8 * 16 * 16)
        assert result["got"]["cav2"][1] == pytest.approx(0.25 * 8 * 16 * 16)
        assert result["rejected"] == ["unsigned", "unsigned"]  # each publisher's first, in order
        for p in pubs:
            p.wait(timeout=15)
    finally:
        for p in [sub, *pubs]:
            if p.poll() is None:
                p.kill()
                p.wait()
    assert time.monotonic() - t0 < 30
