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

from agents.common import START_TIMEOUT_S, AgentArgs, Bus, parse_agent_args, run_agent
from agents.progress import report_progress
from agents.timing import StageTimer, write_timing
from v2vsim.traffic import make_backend
from v2vsim.world.serialize import static_to_bytes, world_to_bytes


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

    def wait_acks(k: int) -> None:
        while not all(acks.get(e, -1) >= k for e in egos if bus.is_alive(f"ego.{e}")):
            ack_event.wait(0.5)
            ack_event.clear()

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
                bus.put("world", world_to_bytes(world))
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
