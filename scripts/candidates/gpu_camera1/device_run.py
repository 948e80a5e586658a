"""One device call: sense the traffic-only camera dataset with one process pool (sense_all.py), calibrate the
camera `single` stage's throughput meanwhile on the first two runs sensed, then train `v2vsim train --stage single
--encoder sinbevt --device cuda --bf16` with epochs x samples chosen to end (validation and export included)
before HARD seconds after T0, and copy the results to OUT.

Environment: T0 (epoch seconds of the call's start), HARD (s), OUT, SRC (traffic dataset), WORK (scratch), N
(train seeds per network), POOL (sensing processes), DEVICE, WORKERS, THREADS, EPOCHS, CALIB_STEPS,
FRAMES ("150,100"), FORCE_PLAN ("epochs,samples,val_samples": skips the throughput plan; local tests).
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor, wait
from multiprocessing import get_context
from pathlib import Path


def _sibling(name: str):
    """A script beside this one, loaded by its path: these scripts are files run on the device machine, not a
    package, and an `import sense_all` reads as a third-party dependency (as run: `sys.path` + `import`)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name(f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


groups = _sibling("sense_all").groups

E = os.environ
T0 = float(E.get("T0", time.time()))
HARD = float(E.get("HARD", "530"))
OUT = Path(E["OUT"])
SRC, WORK = Path(E.get("SRC", "gpucam/data")), Path(E.get("WORK", "/tmp/cam"))
N, POOL, CHUNK = int(E.get("N", "24")), int(E.get("POOL", "14")), int(E.get("CHUNK", "50"))
DEVICE, WORKERS, THREADS = E.get("DEVICE", "cuda"), int(E.get("WORKERS", "12")), int(E.get("THREADS", "16"))
EPOCHS, CALIB_STEPS, BATCH = int(E.get("EPOCHS", "8")), int(E.get("CALIB_STEPS", "30")), int(E.get("BATCH", "8"))
TF, VF = (int(x) for x in E.get("FRAMES", "150,100").split(","))
CAL_RUNS = (("scenarios/intersection.yaml", 100), ("scenarios/intersection.yaml", 90))


def el() -> float:
    return time.time() - T0


def say(msg: str) -> None:
    print(f"[{el():6.1f} s] {msg}", flush=True)


def main() -> int:
    from v2vsim.config import load_scenario
    from v2vsim.data.layout import run_name
    from v2vsim.data.record import _prepare_sensing, _sense_job, record_dataset

    data, calib = WORK / "data", WORK / "calib"
    if data.exists():
        shutil.rmtree(data)
    shutil.copytree(SRC, data)
    plan = groups(N, TF, VF)
    chunks, by_run = [], {}
    for path, seeds, frames, split, ov in plan:
        for s in seeds:
            sc = load_scenario(path, (*ov, f"seed={s}"))
            run_dir = data / run_name(sc.name, s)
            meta = json.loads((run_dir / "traffic" / "traffic.json").read_text())  # recorded here: no simulator
            assert meta["frames_asked"] == frames and meta["overrides"] == list(sc.overrides), (run_dir, meta)
            _prepare_sensing(run_dir, True, sc.overrides)
            by_run[(path, s)] = (run_dir, frames, split, ov)
            first = (path, s) in CAL_RUNS
            for lo in range(0, meta["frames"], CHUNK):
                chunks.append((not first, (path, s, frames, data, ov, True, lo, lo + CHUNK)))
    chunks.sort(key=lambda c: c[0])  # the calibration runs' chunks first (a stable sort keeps the rest in order)
    say(f"sensing {len(by_run)} runs, {len(chunks)} chunks, {POOL} processes")
    cal_proc = None
    frames_done = 0
    with ProcessPoolExecutor(POOL, mp_context=get_context("spawn")) as pool:
        futs = {pool.submit(_sense_job, j): j for _, j in chunks}
        cal_futs = [f for f, j in futs.items() if (j[0], j[1]) in CAL_RUNS]
        wait(cal_futs)
        for f in cal_futs:
            f.result()
        calib.mkdir(parents=True, exist_ok=True)
        for key in CAL_RUNS:
            run_dir, frames, split, ov = by_run[key]
            subprocess.run(["cp", "-al", str(run_dir), str(calib / run_dir.name)], check=True)
            record_dataset(key[0], [key[1]], frames, calib, split=split, overrides=ov, cameras=True, jobs=1,
                           log=open(os.devnull, "w"))
        say("calibration dataset ready; calibrating beside the sensing")
        cal_proc = subprocess.Popen([sys.executable, str(Path(__file__).parent / "calib.py"), str(calib), DEVICE,
                                     str(CALIB_STEPS), str(BATCH), "3", "2"], stdout=subprocess.PIPE, text=True)
        last = time.time()
        pending = set(futs)
        while pending:
            done, pending = wait(pending, timeout=15)
            for f in done:
                frames_done += f.result()[1]
            if time.time() - last > 15 or not pending:
                say(f"sensed {frames_done} frames ({len(pending)} chunks left)")
                last = time.time()
    for path, seeds, frames, split, ov in plan:  # the project's manifest writer: every frame is on disk
        record_dataset(path, seeds, frames, data, split=split, overrides=ov, cameras=True, jobs=1,
                       log=open(os.devnull, "w"))
    man = json.loads((data / "manifest.json").read_text())
    n_train = sum(r["frames"] for r in man["runs"] if r["split"] == "train")
    n_val = sum(r["frames"] for r in man["runs"] if r["split"] == "val")
    say(f"dataset complete: {len(man['runs'])} runs, {n_train} train + {n_val} val frames; "
        f"{shutil.disk_usage(WORK).used / 2**30:.1f} GiB used on its disk")
    shutil.copy(data / "manifest.json", OUT / "dataset_manifest.json")
    try:
        cal_out, _ = cal_proc.communicate(timeout=float(E.get("CALIB_WAIT", "45")))
    except subprocess.TimeoutExpired:
        cal_proc.kill()
        cal_out = ""
        say("calibration still running after the sensing (+CALIB_WAIT s): killed; conservative plan")
    cal = None
    for line in cal_out.splitlines():
        if line.startswith("CALIB "):
            cal = json.loads(line[6:])
    say(f"calibration: {cal}")

    t_now = el()
    if cal is None:  # conservative: 60 samples/s, validation 1 s a sample (16 threads)
        cal = {"step_s": BATCH / 60.0, "load_s_per_sample": 0.0, "collate_s_per_batch": 0.0,
               "val_s_per_sample": THREADS / 2 / 1.5, "keys_s_per_frame": 0.003, "fallback": True}
    gpu_rate = BATCH / cal["step_s"]
    load_rate = WORKERS / (cal["load_s_per_sample"] + cal["collate_s_per_batch"] / BATCH + 1e-9)
    rate = 0.88 * min(gpu_rate, 0.8 * load_rate)
    # validation runs in the training process after the last epoch on THREADS threads (calibrated beside the
    # sensing on 2 threads: pessimistic, then scaled by 2 / THREADS x 3: threads scale sublinearly); at most ~45 s of it
    val_per = cal["val_s_per_sample"] * 2 / THREADS * 3.0
    val_n = int(max(24, min(120, 45.0 / max(val_per, 1e-3))))
    val_s = val_n * val_per
    startup = 20.0 + (n_train / 4 + n_val) * 4 * cal["keys_s_per_frame"]  # model, CUDA, dataset index
    train_s = HARD - t_now - startup - val_s - 10.0 - 3.0 * EPOCHS  # 10 s: export; 3 s an epoch: workers
    epochs = EPOCHS
    samples = max(50 * BATCH, int(rate * train_s / epochs) // BATCH * BATCH)
    say(f"plan: gpu {gpu_rate:.1f} samples/s, loader {load_rate:.1f} samples/s -> {rate:.1f} samples/s; startup "
        f"{startup:.0f} s, train {train_s:.0f} s, validation {val_n} samples ~{val_s:.0f} s: {epochs} x {samples}")
    if E.get("FORCE_PLAN"):
        epochs, samples, val_n = (int(x) for x in E["FORCE_PLAN"].split(","))
        say(f"FORCE_PLAN: {epochs} x {samples}, validation {val_n}")
    plan_doc = {"calibration": cal, "epochs": epochs, "samples_per_epoch": samples, "val_samples": val_n,
                "rate_planned": rate, "t_plan_s": t_now, "n_train_frames": n_train, "n_val_frames": n_val}
    (OUT / "plan.json").write_text(json.dumps(plan_doc, indent=1))
    say(f"plan: {epochs} epochs x {samples} samples, batch {BATCH}, validation {val_n} samples after the last")
    zoo, work = WORK / "zoo", WORK / "work"
    cmd = [sys.executable, "-m", "v2vsim.cli", "train", "--data", str(data), "--stage", "single", "--encoder",
           "sinbevt", "--out", str(zoo), "--work", str(work), "--resume", "--device", DEVICE, "--bf16", "--threads",
           str(THREADS), "--workers", str(WORKERS), "--epochs", str(epochs), "--samples-per-epoch", str(samples),
           "--batch", str(BATCH), "--val-every", str(epochs), "--val-samples", str(val_n)]
    say("train: " + " ".join(cmd[2:]))
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)

    def pump() -> None:
        for line in proc.stdout:
            say(line.rstrip("\n"))

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    killed = False
    while proc.poll() is None:
        if el() > HARD and not killed:
            say("HARD limit reached: stopping the training (its last.pt holds the last finished epoch)")
            os.killpg(proc.pid, signal.SIGTERM)
            killed = True
        time.sleep(0.5)
    reader.join(timeout=5)
    say(f"train exited {proc.returncode}")
    single = zoo / "sinbevt_tiny" / "single.pt"
    if (work / "single" / "last.pt").is_file():
        import torch

        ck = torch.load(work / "single" / "last.pt", map_location="cpu", weights_only=False)
        (OUT / "history.json").write_text(json.dumps({"epoch": ck["epoch"], "step": ck["step"], "wall_s": ck["wall_s"],
                                                      "history": ck["history"]}, indent=1, default=str))
    if single.is_file():
        shutil.copy(single, OUT / "single.pt")
        shutil.copy(zoo / "manifest.json", OUT / "manifest.json")
        say(f"copied {single} ({single.stat().st_size} B) and the zoo manifest to OUT")
    elif (work / "single" / "last.pt").is_file():
        import torch

        ck = torch.load(work / "single" / "last.pt", map_location="cpu", weights_only=False)
        torch.save({"model": ck["model"], "epoch": ck["epoch"], "step": ck["step"], "history": ck["history"]},
                   OUT / "partial_last_model.pt")
        say(f"no single.pt: saved the model of last.pt (epoch {ck['epoch']}, step {ck['step']}) to OUT")
    return proc.returncode or 0


if __name__ == "__main__":
    sys.exit(main())
