"""`v2vsim evaluate RECORDING_DIR`: the ego of a recorded run (output.record_messages) replayed with other
receiver-side keys: no SUMO, sensing or encoding; the same decoder, channel models, fusion, scoring, report and
plots as a live run (agents.ego.ego_loop itself, over agents.ego_replay.ReplayBus). docs/run.md "Record once,
evaluate many".

Receiver-side keys (RECEIVER_SIDE) may differ from the recording; any other key that differs changed what the
CAVs sent, and is a ConfigError naming it (exit 2).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

from v2vsim.config import ConfigError, Scenario, check_output_dir, load_scenario

# What acts only at the receiver: a key equal to one of these, or under one (dotted prefix).
RECEIVER_SIDE = (
    "name", "duration_s", "comm.range_m", "comm.latency_ms", "comm.drop", "comm.bandwidth_mbps", "comm.max_age_ms",
    "comm.fusion_deadline_ms", "comm.compensation", "comm.pose_noise", "comm.channel", "comm.medium",
    "perception.methods", "evaluation", "output", "transport.pipeline",
    "transport.mode", "transport.connect", "transport.listen",  # how the processes met: no bus in a replay
)


def receiver_side(key: str) -> bool:
    return any(key == r or key.startswith(r + ".") for r in RECEIVER_SIDE)


def _needed_kinds(methods: tuple[str, ...], lidar: bool) -> list[str]:
    """The V2V kinds the ego takes for these methods (agents.ego.ego_loop)."""
    return ["features"] + (["points"] if "early" in methods and lidar else []) + (
        ["outputs"] if "late" in methods else [])


def evaluate(recording: Path, overrides: list[str], out: Path, frames: int | None = None) -> int:
    from v2vsim.recording.messages import Recording, resolved_keys

    try:
        rec = Recording(recording)
    except (OSError, ValueError) as e:
        raise ConfigError(str(e)) from None
    h = rec.header
    source = Path(h["scenario"]["source"])
    if not source.exists():
        source = rec.folder / "scenario.yaml"
    sc = load_scenario(source, [*h["scenario"]["overrides"], *overrides])
    sc = dataclasses.replace(sc, output=dataclasses.replace(sc.output, record_messages=False))
    before, now = h["scenario"]["resolved"], resolved_keys(sc)
    defaults = resolved_keys(Scenario())  # a key added since the recording was made: it ran with the default
    for key in sorted(set(before) | set(now)):
        if key in ("output.record_messages",) or receiver_side(key):
            continue
        if before.get(key, defaults.get(key)) != now.get(key):
            raise ConfigError(f"{key}: {now.get(key)!r} differs from the recording's {before.get(key)!r}; it is a "
                              "sender-side key (it changes what the CAVs sent): record a new run for it")
    lidar = sc.perception.modality == "lidar"
    for kind in _needed_kinds(sc.perception.methods, lidar):
        if kind not in h["kinds"]:
            raise ConfigError(f"perception.methods: {', '.join(sc.perception.methods)} needs {kind} messages, which "
                              "the recording lacks (record with a method that takes them: early for points, "
                              "late for outputs)")
    if sc.output.rerun and "scan" not in h["side"]:
        raise ConfigError("output.rerun: true needs the CAVs' scans, which the recording lacks (it was recorded "
                          "with output.rerun false); use --set output.rerun=false")
    n = int(h["frames_requested"])
    if not rec.complete:  # killed mid-way: what it recorded, up to the last whole frame
        try:
            n = min(n, sum(1 for _ in rec.frames()))
        except (OSError, ValueError) as e:
            raise ConfigError(str(e)) from None
        if n == 0:
            raise ConfigError(f"{recording}: the recorded run ended before its first frame was recorded (status "
                              f"{h.get('status')!r}): nothing to replay")
        print(f"v2vsim evaluate: {recording}: the recorded run never finished (status {h.get('status')!r}: killed?); "
              f"replaying the {n} frame(s) it recorded whole", file=sys.stderr)
    if frames is not None:
        if not 1 <= frames <= n:
            raise ConfigError(f"--frames {frames}: the recording has {n} frames; allowed: 1..{n}")
        n = frames
    if out.resolve() in (rec.folder.resolve(), rec.folder.parent.resolve()):
        raise ConfigError(f"--out {out}: the recorded run's own folder; its metrics.json and report would be "
                          "overwritten: choose another folder")
    check_output_dir(out, "--out")
    from v2vsim.perception.build import check_scenario

    check_scenario(sc)
    from agents.common import AgentArgs
    from agents.ego import ego_loop
    from agents.ego_replay import ReplayBus

    args = AgentArgs(scenario=sc, scenario_path=str(source), overrides=tuple(sc.overrides), run_id=h["run_id"],
                     listen="", peers=(), cavs=tuple(h["cavs"]), egos=(h["ego"],), cav=h["ego"], frames=n,
                     out=str(out))
    bus = ReplayBus(rec, n)
    return ego_loop(args, bus, replay=bus)  # type: ignore[arg-type]
