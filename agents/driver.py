"""Simulator driver process: steps the traffic backend and publishes each WorldState.

lockstep: frame k+1 is published only after every ego acknowledged frame k - transport.pipeline,
so the CAVs sense and encode the next frames while the egos fuse this one, and the run is still
deterministic for a seed (egos fuse frames in order, each once all its messages are in). realtime: frames go out at
rate_hz on the wall clock whether or not anyone kept up. In both, the driver stops (exit 1) once
every ego process is gone: nobody would fuse what it publishes.
"""

from __future__ import annotations

import json
import sys
import threading
import time

from agents.args import AgentArgs, parse_agent_args
from agents.bus import START_TIMEOUT_S, Bus
from agents.lifecycle import run_agent
from agents.progress import report_progress
from agents.timing import StageTimer, write_timing
from v2vsim.traffic import make_backend
from v2vsim.world.serialize import static_to_bytes, world_to_bytes

ACK_RESEND_S = 2.0  # an ego silent this long gets the worlds it has not acked again
HANG_TIMEOUT_S = 120.0  # no ack for this long ends the run (exit 1, why on stderr); the ego waits 60 s for a CAV


def drive(args: AgentArgs, bus: Bus) -> int:
    sc = args.scenario
    frames = args.frames or sc.frames
    egos = args.egos
    acks: dict[str, int] = {}
    ack_event = threading.Event()

    def on_ack(sender: str, payload: bytes) -> None:
        # The Bus admits acks only from ego processes (signed under comm.auth); the ego is the key's
        # sender, not what the payload claims, and an old (replayed) frame never moves an ack back.
        if sender not in egos:
            return
        try:
            frame = int(json.loads(payload)["frame"])
        except (ValueError, KeyError, TypeError):
            return  # a malformed ack is ignored, never fatal
        acks[sender] = max(acks.get(sender, -1), frame)
        ack_event.set()

    def egos_gone(k: int) -> bool:
        """Nobody fuses any more: publishing the rest of the run would be work for no one."""
        if any(bus.is_alive(f"ego.{e}") for e in egos):
            return False
        print(f"v2vsim-driver: every ego process is gone at frame {k}; stopping", file=sys.stderr, flush=True)
        return True

    recent: dict[int, bytes] = {}  # the worlds an ego may still wait for (frames past the oldest ack)

    def wait_acks(k: int) -> None:
        """Until every live ego acked frame k. An ego that has not for ACK_RESEND_S is sent the worlds it has
        not acked again (it may have missed them, e.g. joining late; agents ignore a world they have had);
        one that has not for HANG_TIMEOUT_S is a TimeoutError: the run cannot go on, and says why."""
        t0 = resent = time.monotonic()
        while not all(acks.get(e, -1) >= k for e in egos if bus.is_alive(f"ego.{e}")):
            ack_event.wait(0.5)
            ack_event.clear()
            now = time.monotonic()
            late = [e for e in egos if bus.is_alive(f"ego.{e}") and acks.get(e, -1) < k]
            if late and now - t0 > HANG_TIMEOUT_S:
                raise TimeoutError(f"no ack for frame {k} from ego {', '.join(late)} within {HANG_TIMEOUT_S:g} s")
            if late and now - resent > ACK_RESEND_S:
                oldest = min(acks.get(e, -1) for e in late)
                for f in sorted(f for f in recent if f > oldest):
                    bus.put("world", recent[f])
                resent = now
        for f in [f for f in recent if f <= min((acks.get(e, -1) for e in egos), default=k)]:
            del recent[f]

    timer = StageTimer()
    backend = make_backend(sc)
    try:
        world = backend.reset()
        bus.serve("static", static_to_bytes(backend.static))
        bus.subscribe("ack", on_ack)
        bus.ready()
        expected = {f"cav.{c}" for c in args.cavs} | {f"ego.{e}" for e in egos}
        bus.wait_alive(expected, START_TIMEOUT_S)
        bus.put("start", json.dumps({"frames": frames, "wall_t0": time.time()}).encode())
        report_progress("driver", 0, frames)
        t_start = time.monotonic()
        ahead = sc.transport.pipeline
        for k in range(frames):
            if egos_gone(k):
                return 1
            with timer.stage("stepping"):
                if k > 0:
                    world = backend.step()
            with timer.stage("comm"):
                recent[k] = world_to_bytes(world)
                bus.put("world", recent[k])
            timer.frame_done()
            with timer.stage("wait"):
                if sc.transport.clock == "realtime":
                    next_tick = t_start + (k + 1) / sc.rate_hz
                    time.sleep(max(0.0, next_tick - time.monotonic()))
                else:  # frame k+1 may go out once every live ego has fused frame k - pipeline
                    wait_acks(k - ahead)
            report_progress("driver", k + 1, frames)
        if sc.transport.clock != "realtime":
            wait_acks(frames - 1)  # CAVs end on `done`: not before the egos have everything they need
        bus.put("done", json.dumps({"frames": frames}).encode())
    finally:
        backend.close()
        write_timing(args.out, "driver", timer)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = parse_agent_args("driver", argv)
    return run_agent(args, "driver", "main", lambda bus: drive(args, bus))


if __name__ == "__main__":
    sys.exit(main())
