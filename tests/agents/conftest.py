"""Fixtures of the agents' tests: loopback zenoh sessions and a `v2vsim router` process."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator

import pytest
import zenoh

from v2vsim.comm import transport as T
from v2vsim.config import TransportConfig

Sessions = tuple[zenoh.Session, zenoh.Session, zenoh.Session]


def client_session(endpoint: str) -> zenoh.Session:
    """A zenoh client of the router at `endpoint`, as an agent on another host (or an attacker) joins a run."""
    return T.open_session(TransportConfig(mode="client", connect=(endpoint,)))


def _listening(peers: list[str]) -> tuple[zenoh.Session, str]:
    for attempt in range(5):  # free_port can race with another process: take another one
        port = T.free_port()
        try:
            return T.open_session(TransportConfig(), port, peers=peers), T.loopback_endpoint(port)
        except T.TransportError:
            if attempt == 4:
                raise
    raise AssertionError("unreachable")


@pytest.fixture
def sessions() -> Iterator[Sessions]:
    """The ego's session, the driver's, and an attacker's linked to both (peers do not forward)."""
    ego, ego_ep = _listening([])
    driver, driver_ep = _listening([ego_ep])
    attacker = T.open_session(TransportConfig(), peers=[ego_ep, driver_ep])
    try:
        yield ego, driver, attacker
    finally:
        for s in (attacker, driver, ego):
            s.close()


@pytest.fixture
def router() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{T.free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "v2vsim.cli", "router", "--listen", endpoint],
                            stderr=subprocess.PIPE, text=True)
    try:
        assert "listening" in proc.stderr.readline()  # type: ignore[union-attr]
        yield endpoint
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=10)


