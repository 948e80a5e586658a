"""An agent process's life (`run_agent`): the bus opened for its body and closed after it, with a `bye` saying how
it ended; SIGINT and SIGTERM raised as `Stop` so that `finally` blocks run and files get written; an expected
failure (a transport error, a timeout) as one line on stderr."""

from __future__ import annotations

import dataclasses
import signal
import sys
from collections.abc import Callable

from agents.args import AgentArgs, run_signer
from agents.bus import Bus
from v2vsim.comm.control import ENVELOPE_BYTES, ControlPolicy
from v2vsim.comm.transport import TransportError, open_session


class Stop(BaseException):
    """Raised in the main thread on SIGINT/SIGTERM so that `finally` blocks run and files get written.

    A BaseException, as KeyboardInterrupt is: it may be raised inside any code the main thread runs, and code that
    turns every Exception into a result must not swallow it (the codec's "a bug or an input no check foresaw is a
    rejection" turned a Ctrl-C during a decode into a `bad_header` rejection, and the ego went on)."""


def _raise_stop(signum: int, frame: object) -> None:
    raise Stop(signum)


ZENOH_SLACK_BYTES = 64 << 10  # what zenoh adds around a payload (key expression, headers)


def receive_bound(largest: int | None) -> int | None:
    """The zenoh message bound of a process whose longest accepted message is `largest` bytes (None: no bound):
    zenoh drops a message far longer before reassembling it, so a 64 MiB message for a process that takes at
    most 16 MiB costs it no 64 MiB buffer (issue 45; zenoh 1.10 enforces it reliably only over ~16 MiB, and the
    Bus checks each kind's own bound, before copying, for the rest)."""
    return None if largest is None else max(1 << 20, largest + ENVELOPE_BYTES + ZENOH_SLACK_BYTES)


def run_agent(args: AgentArgs, role: str, ident: str, body: Callable[[Bus], int],
              max_message_bytes: int | None = None) -> int:
    """Open the bus, run `body`, and turn every expected failure into a one-line error. max_message_bytes: the
    zenoh bound of the process's session (receive_bound)."""
    signal.signal(signal.SIGTERM, _raise_stop)
    signal.signal(signal.SIGINT, _raise_stop)
    tcfg = args.scenario.transport
    if tcfg.mode == "client":
        tcfg, peers = dataclasses.replace(tcfg, listen=()), ()
    else:
        tcfg, peers = dataclasses.replace(tcfg, listen=(args.listen,) if args.listen else ()), args.peers
    try:
        session = open_session(tcfg, peers=peers, max_message_bytes=max_message_bytes)
    except TransportError as e:
        print(f"v2vsim-{role}: error: {e}", file=sys.stderr)
        return 2
    bus = Bus(session, args.run_id, f"{role}.{ident}", key=run_signer(args),
              policy=ControlPolicy.for_run(args.cavs, args.egos))
    args.startup.mark("zenoh")
    code, why = 1, "crashed"
    try:
        code, why = body(bus), "finished"
        return code
    except Stop as stop:
        code, why = 128 + int(stop.args[0]), f"stopped by signal {stop.args[0]}"
        return code  # the shell's convention for "ended by signal N"
    except TimeoutError as e:
        print(f"v2vsim-{role} {ident}: error: {e}", file=sys.stderr)
        code, why = 1, str(e)
        return 1
    except BaseException as e:
        why = f"{type(e).__name__}: {e}"
        raise
    finally:
        bus.say_bye(code, why)
        bus.close()
