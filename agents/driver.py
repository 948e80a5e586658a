"""Simulator driver process: steps the traffic backend and publishes each WorldState.

lockstep: frame k+1 is published only after every ego acknowledged frame k - transport.pipeline,
so the CAVs sense and encode the next frames while the egos fuse this one, and the run is still
deterministic for a seed (egos fuse frames in order, each once all its messages are in). realtime: frames go out at
rate_hz on the wall clock whether or not anyone kept up. In both, the driver stops (exit 1) once
every ego process is gone: nobody would fuse what it publishes. An ack for a frame the driver has not
published is refused and counted (timing/driver.json control_rejections), never believed.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

from agents.args import AgentArgs, parse_agent_args
from agents.bus import START_TIMEOUT_S, Bus
from agents.lifecycle import receive_bound, run_agent
from agents.progress import report_progress
from agents.timing import StageTimer, write_timing
from v2vsim.comm.codec import RejectedMessage
from v2vsim.comm.control import MAX_CONTROL_BYTES
from v2vsim.control.measures import ssm_conflicts
from v2vsim.traffic import make_backend
from v2vsim.world.serialize import MAX_STATIC_BYTES, MAX_WORLD_BYTES, static_to_bytes, world_to_bytes
from v2vsim.world.state import WorldState

ACK_RESEND_S = 2.0  # an ego silent this long gets the worlds it has not acked again
MAX_COMMAND_MPS2 = 50.0  # a commanded acceleration beyond this is no plan: refused and counted
HANG_TIMEOUT_S = 120.0  # no ack for this long ends the run (exit 1, why on stderr); the ego waits 60 s for a CAV


def parse_ack(payload: bytes, published: int, closed_loop: bool) -> tuple[int, float | None]:
    """An ego's ack: (the frame it fused, the acceleration its planner commanded on it, None without one or in
    an open loop). RejectedMessage (counted by the Bus, never fatal) for an ack without a frame, one for a frame
    not published yet (`published`: the newest on the bus), or a command that is no acceleration in
    [-MAX_COMMAND_MPS2, MAX_COMMAND_MPS2] (NaN and infinities included)."""
    try:
        doc = json.loads(payload)
        frame = int(doc["frame"])
    except (ValueError, KeyError, TypeError):
        raise RejectedMessage("bad_header", "an ack without a frame") from None
    if frame > published:
        raise RejectedMessage("out_of_window", f"ack for frame {frame}, the newest published is {published}")
    command = doc.get("command")
    if command is None or not closed_loop:
        return frame, None
    try:
        accel = float(command["accel"])
    except (KeyError, TypeError, ValueError):
        raise RejectedMessage("bad_header", "a command without an acceleration") from None
    if not -MAX_COMMAND_MPS2 <= accel <= MAX_COMMAND_MPS2:  # NaN fails this too
        raise RejectedMessage("bad_header", f"a commanded acceleration of {accel} m/s^2")
    return frame, accel


def drive(args: AgentArgs, bus: Bus) -> int:
    sc = args.scenario
    frames = args.frames or sc.frames
    egos = args.egos
    acks: dict[str, int] = {}
    ack_event = threading.Event()
    published = [-1]  # the newest frame put on the bus (set before its world goes out)
    # closed loop: ego -> frame -> the acceleration its planner commanded on that frame's perception (with its ack)
    closed_loop = sc.control is not None
    plans: dict[str, dict[int, float]] = {}
    plans_lock = threading.Lock()
    released: set[str] = set()

    def on_ack(sender: str, payload: bytes) -> None:
        # The Bus admits acks only from ego processes (signed under comm.auth); the ego is the key's
        # sender, not what the payload claims, and an old (replayed) frame never moves an ack back.
        # An ack for a frame not published yet cannot be an ego's: believed, one forged ack for frame
        # 10**6 let the driver publish the whole run at once and end it. Refused ones are counted by
        # the Bus (control_rejections, in timing/driver.json), never fatal.
        if sender not in egos:
            return
        frame, accel = parse_ack(payload, published[0], closed_loop)
        if accel is not None:
            with plans_lock:  # the ego plans its own vehicle, and only that one
                plans.setdefault(sender, {})[frame] = accel
        acks[sender] = max(acks.get(sender, -1), frame)
        ack_event.set()

    def egos_gone(k: int) -> bool:
        """Nobody fuses any more: publishing the rest of the run would be work for no one."""
        if any(bus.is_alive(f"ego.{e}") for e in egos):
            return False
        print(f"v2vsim-driver: every ego process is gone at frame {k}; stopping", file=sys.stderr, flush=True)
        return True

    # lockstep: the worlds an ego may still wait for (frames past the oldest ack: at most transport.pipeline + 1);
    # realtime has no acks and resends nothing, so it keeps none
    recent: dict[int, bytes] = {}

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

    def actuate(k: int) -> None:
        """Before the step that makes frame k: each driven vehicle's plan of frame k - 1 - actuation delay
        (lockstep: its ack is in, since the driver waited for frame k - 1 - pipeline); realtime: the newest plan
        that has arrived. A vehicle whose ego is gone goes back to SUMO's driver."""
        due = k - 1 - sc.actuation_delay_frames
        speeds = {}
        with plans_lock:
            for e in egos:
                mine = plans.get(e, {})
                if sc.transport.clock == "realtime":
                    if mine:
                        speeds[e] = mine[max(mine)]
                        mine.clear()
                elif due in mine:
                    speeds[e] = mine.pop(due)
                    for old in [f for f in mine if f < due]:
                        del mine[old]
        for e in egos:
            if e not in released and bus.was_alive(f"ego.{e}") and not bus.is_alive(f"ego.{e}"):
                backend.release(e)  # type: ignore[attr-defined]
                released.add(e)
                speeds.pop(e, None)
        backend.command(speeds)  # type: ignore[attr-defined]

    timer = StageTimer()
    ssm_file = str(Path(args.out) / "ssm.xml") if closed_loop and args.out else None
    backend = make_backend(sc, ssm_file=ssm_file, closed_loop=closed_loop)
    word: dict | None = None  # what the driver tells the egos as it ends (final_word): computed once
    try:
        world = backend.reset()
        args.startup.mark("sumo")  # the network loaded, the traffic warmed up and the CAVs placed
        for missing in getattr(backend, "missing_actors", lambda: ())():  # a critical actor SUMO had no room for
            print(f"v2vsim-driver: {missing}", file=sys.stderr, flush=True)
        static = static_to_bytes(backend.static)
        if len(static) > MAX_STATIC_BYTES:
            raise ValueError(f"the static map is {len(static)} bytes; agents accept at most {MAX_STATIC_BYTES}")
        bus.serve("static", static)
        bus.subscribe("ack", on_ack)
        bus.ready()
        expected = {f"cav.{c}" for c in args.cavs} | {f"ego.{e}" for e in egos}
        bus.wait_alive(expected, START_TIMEOUT_S)
        args.startup.mark("agents_alive")
        bus.put("start", json.dumps({"frames": frames, "wall_t0": time.time()}).encode())
        report_progress("driver", 0, frames)
        t_start = time.monotonic()
        ahead = sc.transport.pipeline
        last = frames - 1  # the last frame published (earlier when every driven vehicle completed its route)
        for k in range(frames):
            if egos_gone(k):
                return 1
            with timer.stage("stepping"):
                if k > 0:
                    if closed_loop:
                        actuate(k)
                    world = backend.step()
            with timer.stage("comm"):
                data = world_to_bytes(world)
                if len(data) > MAX_WORLD_BYTES:  # every agent would refuse it and wait for a world forever
                    raise ValueError(f"the world of frame {k} is {len(data)} bytes ({len(world.actors)} actors); "
                                     f"agents accept at most {MAX_WORLD_BYTES}")
                if sc.transport.clock != "realtime":
                    recent[k] = data
                published[0] = k
                bus.put("world", data)
            timer.frame_done()
            args.startup.mark("first_frame")
            if closed_loop and routes_completed(world, egos):  # each ego ends on this frame's world; so does the run
                print(f"v2vsim-driver: every driven vehicle completed its route at frame {k}", file=sys.stderr,
                      flush=True)
                last = k
                break
            with timer.stage("wait"):
                if sc.transport.clock == "realtime":
                    next_tick = t_start + (k + 1) / sc.rate_hz
                    time.sleep(max(0.0, next_tick - time.monotonic()))
                else:  # frame k+1 may go out once every live ego has fused frame k - pipeline
                    wait_acks(k - ahead)
            report_progress("driver", k + 1, frames)
        if sc.transport.clock != "realtime":
            wait_acks(last)  # CAVs end on `done`: not before the egos have everything they need
        word = final_word(bus, backend, closed_loop, ssm_file)
        bus.put("done", json.dumps({"frames": last + 1, **word}).encode())
    finally:
        # Stopped (Ctrl-C) or failed: the egos write what they have, and take the SSM conflicts and refusals from
        # this process's bye instead of its done (agents.ego_finish.driver_word).
        bus.leave_word(**(word if word is not None else final_word(bus, backend, closed_loop, ssm_file)))
        write_timing(args.out, "driver", timer, bus.control_rejections(), args.startup)
    return 0


def routes_completed(world: WorldState, egos: list[str]) -> bool:
    """Closed loop: every ego's vehicle completed its route, on this world or before (it has left the simulation)."""
    states = {d.id: d for d in world.driven}
    present = {a.id for a in world.actors}
    return all(states[e].finished if e in states else e not in present for e in egos)


def final_word(bus: Bus, backend: object, closed_loop: bool, ssm_file: str | None) -> dict:
    """What the driver tells the egos as it ends (with its done, or its bye): the control messages it refused
    ({kind: {reason: n}}: forged, replayed or impossible acks and commands) and, in a closed loop, SUMO's SSM
    conflicts per vehicle. SUMO writes its SSM log as it closes, so this closes the backend."""
    backend.close()  # type: ignore[attr-defined]
    refused: dict[str, dict[str, int]] = {}
    for (kind, reason), n in sorted(bus.control_rejections().items()):
        refused.setdefault(kind, {})[reason] = n
    word: dict = {"control_rejections": refused}
    if closed_loop:
        word["ssm_conflicts"] = ssm_conflicts(Path(ssm_file) if ssm_file else None)
    return word


def main(argv: list[str] | None = None) -> int:
    args = parse_agent_args("driver", argv)
    return run_agent(args, "driver", "main", lambda bus: drive(args, bus),  # it takes acks, hellos and byes
                     max_message_bytes=receive_bound(MAX_CONTROL_BYTES))


if __name__ == "__main__":
    sys.exit(main())
