"""Sense a traffic-only camera dataset recorded by `scripts/zoo_data.sh DATA N --traffic-only --cameras
--set perception.modality=camera --set perception.encoder=sinbevt` with ONE process pool over every run's
frame chunks (zoo_data.sh's ten sequential `v2vsim dataset` calls each leave the pool partly idle), then let
the project's own `record_dataset` (jobs=1) write run.json + manifest: it finds every frame already on disk
(same sensing marker) and senses nothing more.

    python3 sense_all.py DATA N JOBS [TRAIN_FRAMES VAL_FRAMES]     (frames: 150 / 100 as zoo_data.sh)
"""

import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

CAM = ("perception.modality=camera", "perception.encoder=sinbevt")


def groups(n: int, tf: int, vf: int):
    """zoo_data.sh's calls: (scenario path, seeds, frames, split, overrides), overrides in its order."""
    out = []
    for sc in ("intersection", "t_junction"):
        first = 100
        for g, density in enumerate((600, 900, 1200, 1500)):
            size = n // 4 + (1 if g < n % 4 else 0)
            if size > 0:
                out.append((f"scenarios/{sc}.yaml", list(range(first, first + size)), tf, "train",
                            (f"traffic.background_per_hour={density}", *CAM)))
            first += size
        out.append((f"scenarios/{sc}.yaml", [90, 91], vf, "val", CAM))
    return out


def main() -> None:
    from v2vsim.config import load_scenario
    from v2vsim.data.layout import run_name
    from v2vsim.data.record import SENSE_CHUNK, _prepare_sensing, _run_traffic, _sense_job, record_dataset

    data, n, jobs = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
    tf, vf = (int(sys.argv[4]), int(sys.argv[5])) if len(sys.argv) > 5 else (150, 100)
    plan = groups(n, tf, vf)
    t0 = time.monotonic()
    work = []
    for path, seeds, frames, _split, ov in plan:
        for s in seeds:
            sc, run_dir, worlds = _run_traffic(path, s, frames, data, ov)  # recorded traffic (no simulator)
            _prepare_sensing(run_dir, True, sc.overrides)
            work += [(path, s, frames, data, ov, True, lo, lo + SENSE_CHUNK)
                     for lo in range(0, len(worlds), SENSE_CHUNK)]
    total_runs = sum(len(g[1]) for g in plan)
    print(f"sense_all: {total_runs} runs, {len(work)} chunks of {SENSE_CHUNK} frames, {jobs} processes "
          f"(traffic loaded in {time.monotonic() - t0:.1f} s)", flush=True)
    done = 0
    with ProcessPoolExecutor(jobs, mp_context=get_context("spawn")) as pool:
        futs = [pool.submit(_sense_job, j) for j in work]
        for i, fut in enumerate(as_completed(futs)):
            done += fut.result()[1]
            if i % 20 == 0 or i + 1 == len(futs):
                el = time.monotonic() - t0
                print(f"sense_all: {i + 1}/{len(futs)} chunks, {done} frames, {el:.0f} s, "
                      f"{done / max(el, 1e-9):.1f} frames/s", flush=True)
    for path, seeds, frames, split, ov in plan:  # the project's own manifest writer (senses nothing: all on disk)
        record_dataset(path, seeds, frames, data, split=split, overrides=ov, cameras=True, jobs=1)
    for path, seeds, _f, _s, ov in plan:
        for s in seeds:
            name = run_name(load_scenario(path, (*ov, f"seed={s}")).name, s)
            assert (data / name / "run.json").is_file(), name
    print(f"sense_all: dataset complete in {time.monotonic() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
