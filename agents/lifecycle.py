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
from v2vsim.comm.control import ControlPolicy
from v2vsim.comm.transport import TransportError, open_session


class Stop(Exception):
    """Raised in the main thread on SIGINT/SIGTERM so that `finally` blocks run and files get written."""


def _raise_stop(signum: int, frame: object) -> None:
    raise Stop(signum)


def run_agent(args: AgentArgs, role: str, ident: str, body: Callable[[Bus], int]) -> int:
    """Open the bus, run `body`, and turn every expected failure into a one-line error."""
    signal.signal(signal.SIGTERM, _raise_stop)
    signal.signal(signal.SIGINT, _raise_stop)
    tcfg = args.scenario.transport
    if tcfg.mode == "client":
        tcfg, peers = dataclasses.replace(tcfg, listen=()), ()
    else:
        tcfg, peers = dataclasses.replace(tcfg, listen=(args.listen,) if args.listen else ()), args.peers
    try:
        session = open_session(tcfg, peers=peers)
    except TransportError as e:
        print(f"v2vsim-{role}: error: {e}", file=sys.stderr)
        return 2
    bus = Bus(session, args.run_id, f"{role}.{ident}", key=run_signer(args),
              policy=ControlPolicy.for_run(args.cavs, args.egos))
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
