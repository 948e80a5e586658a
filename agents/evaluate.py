"""`v2vsim evaluate RECORDING_DIR`: the ego of a recorded run (output.record_messages) replayed with other
receiver-side keys: no SUMO, sensing or encoding; the same decoder, channel models, fusion, scoring, report and
plots as a live run (agents.ego.ego_loop itself, over agents.ego_replay.ReplayBus). docs/run.md "Record once,
evaluate many".

Receiver-side keys (v2vsim.recording.messages.RECEIVER_SIDE) may differ from the recording; any other key that
differs changed what the CAVs sent, and is a ConfigError naming it (exit 2).
"""

from __future__ import annotations

import dataclasses
import json
import sys
import threading
import time
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from v2vsim.config import ConfigError, Scenario, check_output_dir, load_scenario
from v2vsim.evaluation.status import COMPLETE
from v2vsim.recording.messages import receiver_side

if TYPE_CHECKING:
    from agents.args import AgentArgs
    from v2vsim.recording.messages import Recording

def _same_file(path: str, sha256: str) -> bool:
    from models.zoo import sha256 as file_sha256

    try:
        return file_sha256(Path(path)) == sha256
    except OSError:
        return False


def _needed_kinds(methods: tuple[str, ...], lidar: bool) -> list[str]:
    """The V2V kinds the ego takes for these methods (agents.ego.ego_loop)."""
    return ["features"] + (["points"] if "early" in methods and lidar else []) + (
        ["outputs"] if "late" in methods else [])


def read_plan(path: Path) -> list[tuple[list[str], Path]]:
    """`evaluate --plan FILE`: [{"out": DIR, "overrides": ["KEY=VALUE", ...]}, ...] as (overrides, out) pairs."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ConfigError(f"--plan {path}: {e}") from None
    ok = isinstance(doc, list) and doc and all(
        isinstance(d, dict) and isinstance(d.get("out"), str) and isinstance(d.get("overrides", []), list)
        and all(isinstance(o, str) for o in d.get("overrides", [])) for d in doc)
    if not ok:
        raise ConfigError(f'--plan {path}: expected a non-empty JSON list of {{"out": DIR, "overrides": '
                          '["KEY=VALUE", ...]}')
    return [(list(d.get("overrides", [])), Path(d["out"])) for d in doc]


def evaluate(recording: Path, overrides: list[str], out: Path, frames: int | None = None) -> int:
    """Replay the recording once, with `overrides`, into `out`."""
    return evaluate_points(recording, [(overrides, out)], frames)


def evaluate_points(recording: Path, points: Sequence[tuple[Sequence[str], Path]], frames: int | None = None) -> int:
    """Replay the recording once per point (overrides, out) in one pass: one ego_loop thread per point over a
    shared reading of the recording (agents.ego_replay.ReplayShare), so that decoding, the worlds, the ground truth
    and every prediction whose fusion inputs two points share are computed once. Every point is checked before any
    runs. Returns the worst exit code of the points."""
    from v2vsim.recording.messages import Recording

    try:
        rec = Recording(recording)
    except (OSError, ValueError) as e:
        raise ConfigError(str(e)) from None
    outs = [out.resolve() for _, out in points]
    if len(set(outs)) < len(outs):
        raise ConfigError("--out: two points write to the same folder; give each its own")
    many = len(points) > 1
    recorded = _recorded_frames(rec, recording)
    plans = []
    for overrides, out in points:
        try:
            plans.append(_prepare(rec, recorded, list(overrides), out, frames))
        except ConfigError as e:
            raise ConfigError(f"{out}: {e}" if many else str(e)) from None
    if not many:
        from agents.ego import ego_loop
        from agents.ego_replay import ReplayBus

        args, n = plans[0]
        bus = ReplayBus(rec, n)
        code = ego_loop(args, bus, replay=bus)  # type: ignore[arg-type]
    else:
        labels = [f"ego.{args.cav} [{', '.join(o) or out.name}]"
                  for (args, _), (o, out) in zip(plans, points, strict=True)]
        code = _replay_together(rec, [a for a, _ in plans], plans[0][1], labels)
    _say_statuses([out for _, out in points])
    return code


def _say_statuses(outs: Sequence[Path]) -> None:
    """A replayed point that is not complete says so on the terminal, as `v2vsim run` does (a replay of a
    degraded run is degraded the same way: its lost agents are the recording's)."""
    for out in outs:
        try:
            status = json.loads((out / "metrics.json").read_text()).get("status")
        except (OSError, ValueError, AttributeError):
            continue  # a point that wrote nothing: its error was said already
        if status != COMPLETE:
            print(f"v2vsim evaluate: {out}: not complete: {status}", file=sys.stderr)


def _replay_together(rec: Recording, runs: list[AgentArgs], frames: int, labels: list[str]) -> int:
    """Every run's ego_loop on its own thread over one ReplayShare; Ctrl-C stops them all (each writes its
    results as interrupted)."""
    from agents.ego import ego_loop
    from agents.ego_replay import ReplayBus, ReplayShare
    from agents.lifecycle import Stop

    share = ReplayShare(rec, len(runs))
    codes = [0] * len(runs)
    t0 = time.monotonic()

    def replay(i: int) -> None:
        bus = ReplayBus(rec, frames, share, i, label=labels[i])
        try:
            codes[i] = ego_loop(runs[i], bus, replay=bus)  # type: ignore[arg-type]
        except Stop:
            codes[i] = 130
        except BaseException:  # noqa: BLE001 - this point crashed (its metrics.json says so); the others go on
            traceback.print_exc()
            codes[i] = 1
        finally:
            bus.close()

    threads = [threading.Thread(target=replay, args=(i,), name=f"replay-{i}") for i in range(len(runs))]
    for t in threads:
        t.start()
    try:
        for t in threads:
            while t.is_alive():
                t.join(0.5)
    except KeyboardInterrupt:
        share.stop()
        for t in threads:
            t.join()
        return 130
    names = {"ground_truth": "ground truths", "map_assets": "map rasters"}
    shared = ", ".join(f"{share.hits[w]} of {n} {names.get(w, w + 's')}" for w, n in sorted(share.lookups.items()))
    print(f"v2vsim evaluate: {len(runs)} points replayed in one pass in {time.monotonic() - t0:.1f} s; computed "
          f"once and shared: {shared}", file=sys.stderr)
    return max(codes)


def _recorded_frames(rec: Recording, recording: Path) -> int:
    """How many frames the recording holds whole: those its run asked for, or, for a run killed mid-way, up to
    its last whole frame (counted by reading it: once per evaluate, whatever the number of points)."""
    h = rec.header
    n = int(h["frames_requested"])
    if rec.complete:
        return n
    try:
        n = min(n, sum(1 for _ in rec.frames()))
    except (OSError, ValueError) as e:
        raise ConfigError(str(e)) from None
    if n == 0:
        raise ConfigError(f"{recording}: the recorded run ended before its first frame was recorded (status "
                          f"{h.get('status')!r}): nothing to replay")
    print(f"v2vsim evaluate: {recording}: the recorded run never finished (status {h.get('status')!r}: killed?); "
          f"replaying the {n} frame(s) it recorded whole", file=sys.stderr)
    return n


def _prepare(rec: Recording, recorded: int, overrides: list[str], out: Path, frames: int | None
             ) -> tuple[AgentArgs, int]:
    """One point's ego arguments and frame count (of the `recorded` whole frames), after checking that its keys
    are receiver-side, that the recording holds what its methods need, and that --out is a new folder."""
    from v2vsim.recording.messages import resolved_keys

    h = rec.header
    source = Path(h["scenario"]["source"])
    files = h["scenario"].get("files", {})  # {key: {"name", "sha256"}}: the copies in files/
    copies = []
    if not source.exists():  # moved: the recording's own copies of the scenario and the files it names
        source = rec.folder / "scenario.yaml"
        copies = [f"{key}={rec.folder / 'files' / f['name']}" for key, f in files.items()
                  if (rec.folder / "files" / f["name"]).is_file()]
    # the trust mode the run was recorded under (its messages carry its signatures; a recording from before
    # issue 45 without the key ran with identity off, the default then), unless --set names another
    recorded_auth = [f"comm.auth.identity={h['scenario']['resolved'].get('comm.auth.identity', 'off')}"]
    sc = load_scenario(source, [*h["scenario"]["overrides"], *copies, *recorded_auth, *overrides])
    sc = dataclasses.replace(sc, output=dataclasses.replace(sc.output, record_messages=False))
    before, now = h["scenario"]["resolved"], resolved_keys(sc)
    for doc, whose in ((before, "the recording was made closed loop"), (now, "--set makes it closed loop")):
        if any(k.startswith("control.") or (k == "control" and v is not None) for k, v in doc.items()):
            raise ConfigError(f"control: {whose}, and a closed-loop run cannot be replayed: its vehicles drove on "
                              "what was perceived, so any change re-runs the world; run it live (v2vsim run or "
                              "sweep)")
    defaults = resolved_keys(Scenario())  # a key added since the recording was made: it ran with the default
    for key in sorted(set(before) | set(now)):
        # perception.device: where this replay's ego infers (the CAVs' side is in the recording, whatever it ran on)
        if key in ("output.record_messages", "perception.device") or receiver_side(key):
            continue
        if before.get(key, defaults.get(key)) != now.get(key):
            if key in files and now.get(key) and _same_file(now[key], files[key]["sha256"]):
                continue  # the same road network or buildings, elsewhere
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
    n = recorded
    if frames is not None:
        if not 1 <= frames <= n:
            raise ConfigError(f"--frames {frames}: the recording has {n} frames; allowed: 1..{n}")
        n = frames
    if out.resolve() in (rec.folder.resolve(), rec.folder.parent.resolve()):
        raise ConfigError(f"--out {out}: the recorded run's own folder; its metrics.json and report would be "
                          "overwritten: choose another folder")
    check_output_dir(out, "--out")
    from v2vsim.perception.checks import check_scenario

    check_scenario(sc)
    from agents.args import AgentArgs

    args = AgentArgs(scenario=sc, scenario_path=str(source), overrides=tuple(sc.overrides), run_id=h["run_id"],
                     listen="", peers=(), cavs=tuple(h["cavs"]), egos=(h["ego"],), cav=h["ego"], frames=n,
                     out=str(out), run_instance=h.get("run_instance", ""))
    return args, n
