"""A process whose Bus closes while its heartbeat thread is putting must exit cleanly.

CI once saw an agent abort after its last frame ("FATAL: exception not rethrown", SIGABRT): a daemon thread
still inside a zenoh put when the interpreter finalised was ended by pthread_exit on its way back to the GIL,
and the forced unwind through zenoh's Rust frames aborted the process. Bus.close() now joins its threads.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

# a Bus whose heartbeat puts without pause (HEARTBEAT_S 0) to a listening peer, closed mid-stream, then exit
_SCRIPT = textwrap.dedent("""
    import sys, time
    import agents.bus as B
    from v2vsim.comm import transport as T
    from v2vsim.config import TransportConfig
    B.HEARTBEAT_S = 0.0
    port = T.free_port()
    peer = T.open_session(TransportConfig(), port)
    peer.declare_subscriber("v2vsim/closing/**", lambda sample: sum(range(2000)))
    bus = B.Bus(T.open_session(TransportConfig(), peers=[T.loopback_endpoint(port)]), "closing", "cav.cav1",
                key=b"k" * 32)
    bus.ready()
    time.sleep(0.3)
    bus.close()
    peer.close()
    sys.exit(0)
""")


@pytest.mark.parametrize("attempt", range(2))
def test_an_agent_exits_cleanly_when_its_bus_closes_mid_heartbeat(attempt: int) -> None:
    done = subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "FATAL" not in done.stderr, (done.returncode, done.stderr[-2000:])


def test_close_leaves_no_bus_thread_behind() -> None:
    import threading

    import agents.bus as B
    from v2vsim.comm import transport as T
    from v2vsim.config import TransportConfig

    bus = B.Bus(T.open_session(TransportConfig()), "closing", "cav.cav1", key=b"k" * 32)
    bus.ready()
    bus.close()
    assert [t.name for t in threading.enumerate() if t.name.startswith("bus-")] == []
