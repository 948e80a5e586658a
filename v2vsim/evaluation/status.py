"""A run's final `status` (metrics.json, the recording's header, the terminal, a sweep's CSV), in words that tell
the truth: a run that went through every frame but lost agents, or in which a method scored nothing, is not
"complete" but "degraded: ...", naming what happened, so that nobody reads its scores as those of a clean run.

Statuses (docs/run.md "How a run ends"):

- `complete`: every frame, every agent, every method scored;
- `degraded: <what>`: every frame, but CAVs were lost (`cav1-cav3 lost from frame 6, cav5 lost from frame 9`),
  methods scored no frame (`methods with no score: late, cobevt`) or the misbehaviour check flagged a sender
  (`cav1 disagreed in 57 of 100 frames`, `defence`); exit 0, the files are written;
- anything else (ended early, stalled, driver died, interrupted, crashed, ego left the simulation, failed):
  set by the ego or the runner where it happened, and kept as it is here.

Plain functions over plain data (no MethodScore, no files): the ego, a replay, the recording, the runner and
the sweep all import this module, and it imports nothing of theirs.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence

COMPLETE = "complete"
DEGRADED = "degraded"
RUNNING = "running"  # the recording's header while a run is under way (or was killed)
_ID = re.compile(r"(.*?)(\d+)")


def cav_ranges(ids: Iterable[str]) -> str:
    """CAV ids grouped for a reader: three or more consecutive numbers of one prefix as `cav1-cav3`, others
    listed (`cav1, cav2`, `cav0, cav4-cav7`), in numeric order; ids without a number are listed after."""
    numbered: dict[str, list[int]] = {}
    other: list[str] = []
    for i in sorted(set(ids)):
        m = _ID.fullmatch(i)
        if m and not (len(m.group(2)) > 1 and m.group(2).startswith("0")):  # "cav01" would not round-trip
            numbered.setdefault(m.group(1), []).append(int(m.group(2)))
        else:
            other.append(i)
    parts: list[str] = []
    for prefix, nums in sorted(numbered.items()):
        nums.sort()
        start = prev = nums[0]
        for n in [*nums[1:], None]:
            if n is not None and n == prev + 1:
                prev = n
                continue
            if prev - start >= 2:
                parts.append(f"{prefix}{start}-{prefix}{prev}")
            else:
                parts += [f"{prefix}{k}" for k in range(start, prev + 1)]
            if n is not None:
                start = prev = n
    return ", ".join(parts + other)


def lost_text(lost: Mapping[str, int]) -> str:
    """`cav1-cav3 lost from frame 6, cav5 lost from frame 9`: the CAVs lost at each frame, earliest first."""
    by_frame: dict[int, list[str]] = {}
    for cav, frame in lost.items():
        by_frame.setdefault(int(frame), []).append(cav)
    return ", ".join(f"{cav_ranges(cavs)} lost from frame {f}" for f, cavs in sorted(by_frame.items()))


def unscored(ious: Mapping[str, Sequence[float | None]]) -> list[str]:
    """The methods (in the given order) whose every IoU (vehicle visible and all, road, lane) is null: they
    scored no frame, or nothing in any frame. Every modality produces these, so null in all of them is never
    the modality's doing; null in one is no fault (a view without a visible vehicle has no vehicle IoU)."""
    return [m for m, values in ious.items() if all(v is None for v in values)]


def final_status(ended: str, lost: Mapping[str, int], no_score: Sequence[str],
                 disagreed: Mapping[str, tuple[int, int]] | None = None) -> str:
    """The status a run reports: `ended` (how the ego's loop ended) unless it is `complete` and agents were
    lost, methods scored nothing or senders were flagged by the misbehaviour check (`disagreed`: sender -> (frames
    flagged, frames compared)); then `degraded: <what>`. A CAV whose vehicle left the simulation is not in
    `lost` (it ended its agent normally) and degrades nothing."""
    if ended != COMPLETE:
        return ended
    what = [lost_text(lost)] if lost else []
    if no_score:
        what.append(f"methods with no score: {', '.join(no_score)}")
    what += [f"{s} disagreed in {n} of {m} frames" for s, (n, m) in sorted((disagreed or {}).items())]
    return f"{DEGRADED}: {'; '.join(what)}" if what else COMPLETE


_DISAGREED = re.compile(r"\S+ disagreed in \d+ of \d+ frames")


def as_configured(status: str | None) -> bool:
    """Whether a run went as configured: `complete`, or degraded only because the misbehaviour check (`defence`)
    flagged senders. Such a run lost nothing and scored every method; the flag is the check's finding (an attack
    study counts these runs, and a resumed sweep keeps them)."""
    if status == COMPLETE:
        return True
    if not is_degraded(status):
        return False
    return all(_DISAGREED.fullmatch(part.strip()) for part in status.split(":", 1)[1].split(";"))


def is_degraded(status: str | None) -> bool:
    return isinstance(status, str) and status.startswith(f"{DEGRADED}:")


def finished(status: str | None) -> bool:
    """Whether the run went through every frame and wrote its results: complete or degraded (a degraded run's
    recording replays whole, as a complete one's does)."""
    return status == COMPLETE or is_degraded(status)


def explain(status: str) -> str | None:
    """One sentence for report.md under a status that is not `complete` and not self-explanatory."""
    if not is_degraded(status):
        return None
    if as_configured(status):
        return ("Degraded: the misbehaviour check (`defence`) flagged a sender whose maps disagreed with the "
                "others': it may have lied. The run itself went as configured, so a sweep counts its scores; "
                "they are those of a run with that sender in it (fused without it in the flagged frames when "
                "`defence.exclude` is on).")
    return ("Degraded: the run went through every frame, but not as configured (a lost CAV sent nothing from "
            "the frame named; a method with no score scored no frame), so its scores are not those of a clean "
            "run: leave it out of comparisons or run it again (a sweep leaves it out of its intervals).")


def terminal_line(statuses: Mapping[str, str], report: str) -> str:
    """The runner's last line: `v2vsim: done: REPORT` when every ego's status is complete, else what happened
    (per ego when several egos did not complete)."""
    bad = {e: s for e, s in statuses.items() if s != COMPLETE}
    if not bad:
        return f"v2vsim: done: {report}"
    what = next(iter(bad.values())) if len(statuses) == 1 else "; ".join(f"ego {e}: {s}" for e, s in bad.items())
    return f"v2vsim: done, not complete: {what}; report: {report}"
