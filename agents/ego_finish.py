"""The ego's finish (agents.ego.ego_loop's `finally`): however the run ended, the last fused frames are scored,
the driver's last word is heard, and metrics.json, report.md, the plots, the recording and the message tape are
written, with signals held off so that a second Ctrl-C cannot cut them short.
"""

from __future__ import annotations

import time
from collections import Counter

from agents.bus import DRIVER_GRACE_S, Bus
from agents.ego_collect import control_rejections, reject_leftovers
from agents.ego_mailbox import Mailbox
from agents.ego_scoring import signals_deferred
from agents.ego_setup import Ego, EgoRun
from v2vsim.comm.control import DRIVER
from v2vsim.config import Scenario
from v2vsim.control.critical import critical_measures, critical_total
from v2vsim.control.measures import driving_block, vehicle_measures
from v2vsim.control.pilot import Pilot
from v2vsim.control.score import CLOSE_CALL, CLOSE_CALL_PENALTY, PENALTY, safety_block, score_block, total_score
from v2vsim.evaluation.fuse_and_score import box_iou
from v2vsim.evaluation.report import write_outputs
from v2vsim.evaluation.status import final_status, unscored

DONE_WAIT_S = 10.0  # how long an ego at the end of its run waits for the driver's done (SUMO closing, its SSM log)
STOPPING_WAIT_S = 1.5  # the same for an ego that is stopping (Ctrl-C, the driver gone): the runner's grace is 5 s


def finish(ego: Ego, run: EgoRun) -> None:
    """Write the run's results, however it ended (run.status so far); a failure of the scoring of its last frames
    makes it a crash (run.code 1), raised once the files are written."""
    with signals_deferred():  # a second Ctrl-C or the runner's SIGINT must not cut the files short
        late_error: BaseException | None = None
        try:
            ego.after.close()  # every fused frame scored (and recorded) before the files are written
        except Exception as e:
            run.status = crashed_status(f"after frame {run.k}", e)
            late_error, run.code = e, 1
        if ego.pool is not None:  # a Stop may leave a method running on it: let it end
            ego.pool.shutdown(wait=True)
        reject_leftovers(ego.box, ego.wire.kinds, ego.inboxes, ego.wire.decoder)
        went_to_end = run.status == "complete"
        settle_status(ego, run)
        fill_summary(ego, run)
        # the driver's last word (its SSM conflicts and refusals): waited for only live; long only where the
        # driving block needs SUMO's SSM log and the run went to its end (the other egos may still be fusing)
        wait_s = (0.0 if ego.replay is not None else DONE_WAIT_S if ego.pilot is not None and went_to_end
                  else STOPPING_WAIT_S)
        word = driver_word(ego.box, ego.bus, ego.done_doc, wait_s)
        if ego.pilot is not None:
            ego.summary.driving = driving_summary(ego.sc, ego.me, ego.pilot, word, went_to_end)
        control = Counter(ego.bus.control_rejections()) + Counter(driver_refusals(word))
        by_kind = {kind: ib.stats for kind, ib in ego.inboxes.items()}
        by_kind["control"] = control_rejections(control, ego.stats)
        write_outputs(ego.out_dir, ego.summary, ego.scores, ego.stats, by_kind, box_iou)
        close_outputs(ego, run, dict(control))
    if late_error is not None:
        raise late_error


def settle_status(ego: Ego, run: EgoRun) -> None:
    """run.status as metrics.json says it: a run through every frame that lost agents or scored nothing for a
    method says so (a replay too: its lost agents are the recording's, from the same frames)."""
    ious = {m: (s.vehicle.iou, s.vehicle_all.iou, s.road.iou, s.lane.iou) for m, s in ego.scores.items()}
    sender_check = ego.nets.sender_check
    run.status = final_status(run.status, run.lost, unscored(ious),
                              None if sender_check is None else sender_check.flagged_counts())


def fill_summary(ego: Ego, run: EgoRun) -> None:
    """What the summary learns only at the end: how the run went and where its time went."""
    summary, sender_check = ego.summary, ego.nets.sender_check
    summary.timing = ego.timer.to_json() | {"fusion_threads": ego.threads, "startup": ego.args.startup.to_json()}
    summary.defence = None if sender_check is None else sender_check.to_json()
    summary.frames = run.frames_done
    summary.sim_s = (run.k + 1) / ego.sc.rate_hz
    summary.status = run.status
    summary.wall_s = time.monotonic() - run.t_start
    summary.lost_agents = dict(run.lost)
    summary.feature_bytes = dict(ego.inboxes["features"].bytes_by_sender)


def close_outputs(ego: Ego, run: EgoRun, control: dict[tuple[str, str], int]) -> None:
    """Close the recording and the message tape (it records how the run ended), and a replay's bus."""
    if ego.recorder is not None:
        ego.recorder.close()
    if ego.tape is not None:
        ego.tape.close(status=run.status, lost=run.lost, control=control)
    if ego.replay is not None:
        ego.replay.close()


def driver_word(box: Mailbox, bus: Bus, done_doc: dict, wait_s: float) -> dict:
    """What the driver said as it ended: its done ({frames, control_rejections, ssm_conflicts}), or, when it stopped
    or failed first, the same fields in its bye; {} when it died without a word. Waits at most `wait_s`, and not
    once the driver's token has been gone for DRIVER_GRACE_S: a killed driver says nothing more."""
    deadline = time.monotonic() + wait_s
    gone_at = None
    with box.cond:
        while not box.done:
            if bus.farewell(DRIVER) is not None:
                break
            now = time.monotonic()
            if bus.driver_gone():
                gone_at = gone_at or now
                if now - gone_at > DRIVER_GRACE_S:
                    break
            if now >= deadline:
                break
            box.cond.wait(0.1)
    if box.done:
        return done_doc
    return bus.farewell(DRIVER) or {}


def driver_refusals(word: dict) -> dict[tuple[str, str], int]:
    """The control messages the driver refused, from its final word, keyed as the ego's own (kind@driver, reason)
    so that metrics.json comm.rejected_reasons and the report count them too."""
    out: dict[tuple[str, str], int] = {}
    refused = word.get("control_rejections")
    for kind, reasons in (refused.items() if isinstance(refused, dict) else ()):
        for reason, n in (reasons.items() if isinstance(reasons, dict) else ()):
            if isinstance(n, int) and n > 0:
                out[(f"{kind}@driver", str(reason))] = n
    return out


def driving_summary(sc: Scenario, me: str, pilot: Pilot, word: dict, time_limit_reached: bool) -> dict:
    """metrics.json `driving` of this ego's vehicle. SUMO writes its SSM log when the simulation closes, after the
    last frame: the driver counts its conflicts and says them as it ends (`word`, from driver_word); None when it
    never said them (it died). `time_limit_reached`: the run went on until its last frame or the route's end (status
    complete: a route not completed by then is a timeout; a run stopped early is not)."""
    assert sc.control is not None
    conflicts = word.get("ssm_conflicts")
    count = conflicts.get(me, 0) if isinstance(conflicts, dict) else None
    c = sc.control
    header = {"method": c.method, "planner": c.planner, "driven": [me],
              "actuation_delay_frames": sc.actuation_delay_frames,
              "actuation_delay_ms": round(1000.0 * sc.actuation_delay_frames * sc.dt, 3),
              "background_ignore_junction_foes": c.background_ignore_junction_foes,
              "ssm_thresholds": {"ttc_s": c.ssm.ttc_s, "drac_mps2": c.ssm.drac_mps2, "pet_s": c.ssm.pet_s,
                                 "range_m": c.ssm.range_m},
              "hard_brake_mps2": c.hard_brake_mps2, "near_miss_gap_m": c.near_miss_gap_m}
    per = vehicle_measures(pilot.frames, sc.dt, c.hard_brake_mps2, c.near_miss_gap_m, count)
    if per.get("frames"):
        per |= score_block(pilot.frames, per["collisions"], time_limit_reached)
        per |= safety_block(per)
        per |= critical_measures(pilot.frames, pilot.critical)
    block = driving_block({me: per}, {**header, "route_m": c.route_m, "penalties": dict(PENALTY),
                                      "close_call": {**CLOSE_CALL, "penalty": round(CLOSE_CALL_PENALTY, 4)}})
    block["total"] |= total_score([v for v in block["vehicles"].values() if v.get("frames")])
    block["total"] |= critical_total(block["vehicles"], me)
    return block


def crashed_status(where: str, e: BaseException) -> str:
    """metrics.json status of a crash: where, the exception type and its message on one line."""
    return f"crashed {where}: {type(e).__name__}: {' '.join(str(e).split())[:300]}"
