"""One device call that continues the camera candidate zoo models/candidates/gpu_camera1 (its SinBEVT `single.pt`):
sense the carried traffic-only camera dataset in one process pool (../gpu_camera1/sense_all.py), then with
`v2vsim train --encoder sinbevt --device cuda` the feature cache of the zoo's encoder (`--stage cache` with a --work
that has no single/final.pt), `none`, `cobevt`, and further fusion stages while time remains; every stage ends
(validation and export included) before HARD seconds after T0, or is stopped there. The new checkpoints and the
zoo's manifest go to OUT as one tar (zoo.tar), with the per-stage histories (histories.json), the plan and
timings (plan.json) and the dataset's manifest.

Stage sizes: the GPU recipe of scripts/zoo_gpu.sh (EPOCHS x SAMPLES, batch BATCH, validation once after the last
epoch) where it fits. Each stage's duration is predicted from a rate (samples/s; a prior for the first stage that
runs, the measured rate of the stages before it afterwards), its start-up and its validation; a core stage (CORE)
shrinks its samples per epoch to fit (keeping the predicted time of the core stages after it), another stage
runs only when at least MIN_FRACTION of the recipe fits.

Environment: T0 (epoch seconds of the call's start), HARD (s), OUT, SRC (traffic dataset), WORK (scratch),
ZOO_SRC (the zoo to continue), SINGLE (its single.pt, if elsewhere), N (train seeds per network), POOL (sensing
processes), FRAMES ("150,100"), DEVICE,
WORKERS, THREADS, BATCH, EPOCHS, SAMPLES, VAL (validation samples), STAGES (after the cache, in order), CORE,
BF16_STAGES (stages trained with --bf16; default none), MIN_FRACTION, RATES ("stage=samples/s,..." priors),
FORCE ("epochs,samples,val": every stage that size, no plan; local tests).
"""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tarfile
import threading
import time
from pathlib import Path

E = os.environ
T0 = float(E.get("T0", time.time()))
HARD = float(E.get("HARD", "545"))
OUT = Path(E["OUT"])
HERE = Path(__file__).resolve().parent
SRC, WORK = Path(E.get("SRC", "gpucam/data2")), Path(E.get("WORK", "/tmp/cam2"))
ZOO_SRC = Path(E.get("ZOO_SRC", "models/candidates/gpu_camera1"))
N, POOL = int(E.get("N", "12")), int(E.get("POOL", "16"))
TF, VF = (int(x) for x in E.get("FRAMES", "150,100").split(","))
DEVICE, WORKERS, THREADS = E.get("DEVICE", "cuda"), int(E.get("WORKERS", "12")), int(E.get("THREADS", "16"))
BATCH, EPOCHS, SAMPLES, VAL = (int(E.get(k, d)) for k, d in
                               (("BATCH", "8"), ("EPOCHS", "4"), ("SAMPLES", "2400"), ("VAL", "120")))
STAGES = [s for s in E.get("STAGES", "none,cobevt,attfuse,fcooper,v2vnet,disconet").split(",") if s]
CORE = set(E.get("CORE", "none,cobevt").split(","))
BF16 = set(E.get("BF16_STAGES", "").split(",")) - {""}
MIN_FRACTION = float(E.get("MIN_FRACTION", "0.5"))
# Prior rates (samples/s, batch 8, 12 loader processes) until a stage has been measured: guesses from the H100
# LiDAR run (4 x 2,400 in 1.7-2.0 min a stage) for this smaller 32 x 32 camera map; the measured rates replace them,
# scaled by these ratios for a stage not run yet.
PRIOR = {"none": 150.0, "cobevt": 90.0, "attfuse": 110.0, "fcooper": 120.0, "disconet": 100.0, "v2vnet": 70.0}
PRIOR.update({k: float(v) for k, v in (kv.split("=") for kv in E.get("RATES", "").split(",") if kv)})
STARTUP_S, VAL_S, END_S = 20.0, 20.0, 8.0  # priors: a stage's start-up and validation; the copy to OUT at the end
ZOO_NAME = "sinbevt_tiny"
PROGRESS = re.compile(r"^\[(\w+)\] epoch (\d+)/(\d+) step (\d+)/(\d+) .* ([0-9.]+) samples/s")


def el() -> float:
    return time.time() - T0


def say(msg: str) -> None:
    print(f"[{el():6.1f} s] {msg}", flush=True)


def run(cmd: list[str], on_line=None, quiet_prefixes: tuple[str, ...] = ()) -> tuple[int, bool]:
    """Run `cmd` in its own process group, its output line by line through say() (lines ending in a carriage
    return, progress lines, and lines starting with `quiet_prefixes` at most every 10 s); stop it (SIGTERM, then
    SIGKILL) once el() passes HARD. Returns (exit code, whether it was stopped)."""
    say("$ " + " ".join(cmd))
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    last_quiet = [0.0]

    def pump() -> None:
        buf = b""
        while True:
            chunk = proc.stdout.read1(65536)
            if not chunk:
                break
            buf += chunk
            parts = re.split(rb"[\r\n]", buf)
            buf = parts.pop()
            for raw in parts:
                line = raw.decode(errors="replace").rstrip()
                if not line:
                    continue
                if on_line is not None:
                    on_line(line)
                if line.startswith(quiet_prefixes):
                    if time.time() - last_quiet[0] < 10.0:
                        continue
                    last_quiet[0] = time.time()
                say(line)
        if buf.strip():
            say(buf.decode(errors="replace").rstrip())

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    stopped, t_term = False, None
    while proc.poll() is None:
        if el() > HARD and not stopped:
            say("HARD limit reached: stopping it")
            os.killpg(proc.pid, signal.SIGTERM)
            stopped, t_term = True, time.time()
        if stopped and time.time() - t_term > 5:
            os.killpg(proc.pid, signal.SIGKILL)
        time.sleep(0.2)
    reader.join(timeout=5)
    say(f"exit {proc.returncode}")
    return proc.returncode, stopped


def train_cmd(data: Path, zoo: Path, work: Path, stage: str, extra: list[str]) -> list[str]:
    return [sys.executable, "-m", "v2vsim.cli", "train", "--data", str(data), "--stage", stage, "--encoder",
            "sinbevt", "--out", str(zoo), "--work", str(work), "--device", DEVICE, "--threads", str(THREADS),
            *extra]


def predict(stage: str, samples: int, measured: dict) -> tuple[float, float, float, float]:
    """(rate, start-up s, validation s, total s) predicted for `samples` training samples of `stage`."""
    done = [m for m in measured.values() if m.get("rate")]
    prior = PRIOR.get(stage, 80.0)
    if stage in measured and measured[stage].get("rate"):
        rate = measured[stage]["rate"]
    elif done:  # the measured stages' rates, each scaled by the priors' ratio: the most pessimistic, and for a
        # core stage (planned for while an earlier stage is planned) never above its prior
        rate = min(m["rate"] * prior / PRIOR.get(s, 80.0) for s, m in measured.items() if m.get("rate"))
        rate = min(rate, prior) if stage in CORE else rate
    else:
        rate = prior
    startup = max([STARTUP_S] + [m["startup_s"] for m in done])
    val = max([VAL_S] + [m["val_s"] for m in done if m.get("val_s") is not None])
    return rate, startup, val, startup + samples / rate + val


def plan_stage(stage: str, later_core: list[str], measured: dict) -> tuple[int, int, dict]:
    """(epochs, samples per epoch, plan record) for `stage`; samples 0: skip it."""
    if E.get("FORCE"):
        ep, sp, _ = (int(x) for x in E["FORCE"].split(","))
        return ep, sp, {"forced": True}
    full = EPOCHS * SAMPLES
    reserve = sum(predict(s, full, measured)[3] for s in later_core)
    avail = HARD - el() - END_S - reserve
    rate, startup, val, need = predict(stage, full, measured)
    rec = {"t_plan_s": round(el(), 1), "avail_s": round(avail, 1), "reserve_core_s": round(reserve, 1),
           "rate_pred": round(rate, 1), "startup_pred_s": round(startup, 1), "val_pred_s": round(val, 1)}
    if need * 1.1 <= avail:
        samples = SAMPLES
    else:
        fits = (avail / 1.1 - startup - val) * rate  # samples that fit, with a 10 % margin
        per_epoch = int(fits / EPOCHS) // BATCH * BATCH
        floor = 10 * BATCH if stage in CORE else MIN_FRACTION * SAMPLES  # a core stage runs even if short
        if per_epoch < floor:
            rec["skipped"] = f"{max(per_epoch, 0)} samples per epoch fit, under {floor:.0f}"
            return EPOCHS, 0, rec
        samples = per_epoch
    rec["pred_s"] = round(predict(stage, EPOCHS * samples, measured)[3], 1)
    return EPOCHS, samples, rec


def histories(work: Path) -> dict:
    import torch

    out = {}
    for last in sorted(work.glob("*/last.pt")):
        ck = torch.load(last, map_location="cpu", weights_only=False)
        out[last.parent.name] = {"epoch": ck["epoch"], "step": ck["step"], "wall_s": ck["wall_s"],
                                 "spec": ck.get("spec"), "history": ck["history"]}
    return out


def collect(zoo: Path, work: Path, doc: dict) -> None:
    """zoo.tar (the zoo's manifest and every checkpoint but the carried single.pt), histories.json, plan.json."""
    try:
        (OUT / "histories.json").write_text(json.dumps(histories(work), indent=1, default=str))
    except Exception as e:  # noqa: BLE001 (what finished must still reach OUT)
        say(f"histories: {e!r}")
    with tarfile.open(OUT / "zoo.tar", "w") as tar:
        if (zoo / "manifest.json").is_file():
            tar.add(zoo / "manifest.json", "manifest.json")
        for p in sorted((zoo / ZOO_NAME).glob("*.pt")):
            if p.name != "single.pt":
                tar.add(p, f"{ZOO_NAME}/{p.name}")
                doc.setdefault("checkpoints", {})[p.name] = p.stat().st_size
    doc["t_end_s"] = round(el(), 1)
    (OUT / "plan.json").write_text(json.dumps(doc, indent=1))
    say(f"OUT: zoo.tar ({(OUT / 'zoo.tar').stat().st_size} B: manifest + {sorted(doc.get('checkpoints', {}))}), "
        "histories.json, plan.json")


def main() -> int:
    data, zoo, work = WORK / "data", WORK / "zoo", WORK / "work"
    doc: dict = {"hard_s": HARD, "n_seeds": N, "frames": [TF, VF], "device": DEVICE, "workers": WORKERS,
                 "threads": THREADS, "batch": BATCH, "recipe": [EPOCHS, SAMPLES, VAL], "stages": {}}
    for p in (data, zoo, work):
        if p.exists():
            shutil.rmtree(p)
    # the zoo to continue (its manifest and single.pt: load_checkpoint checks the sha256 the manifest records)
    (zoo / ZOO_NAME).mkdir(parents=True)
    shutil.copy(ZOO_SRC / "manifest.json", zoo / "manifest.json")
    # SINGLE: the encoder file itself where ZOO_SRC's single.pt is a symbolic link the device copy may not keep
    shutil.copy(Path(E.get("SINGLE", ZOO_SRC / ZOO_NAME / "single.pt")), zoo / ZOO_NAME / "single.pt")
    shutil.copytree(SRC, data)

    t = el()
    rc, _ = run([sys.executable, str(HERE.parent / "gpu_camera1" / "sense_all.py"), str(data), str(N), str(POOL),
                 str(TF), str(VF)], quiet_prefixes=("dataset ",))
    man = json.loads((data / "manifest.json").read_text()) if (data / "manifest.json").is_file() else None
    if rc != 0 or man is None:
        say("sensing failed")
        collect(zoo, work, doc)
        return 3
    shutil.copy(data / "manifest.json", OUT / "dataset_manifest.json")
    n_train = sum(r["frames"] for r in man["runs"] if r["split"] == "train")
    n_val = sum(r["frames"] for r in man["runs"] if r["split"] == "val")
    doc["sensing"] = {"s": round(el() - t, 1), "runs": len(man["runs"]), "train_frames": n_train,
                      "val_frames": n_val}
    say(f"dataset: {len(man['runs'])} runs, {n_train} train + {n_val} val frames in {el() - t:.0f} s; "
        f"{shutil.disk_usage(WORK).used / 2**30:.1f} GiB used on its disk")

    t = el()
    rc, stopped = run(train_cmd(data, zoo, work, "cache", []), quiet_prefixes=("cache:",))
    cache = work / "cache"
    doc["cache"] = {"s": round(el() - t, 1), "rc": rc, "stopped": stopped}
    if rc != 0 or not (cache / "encoder.json").is_file():
        say("cache failed")
        collect(zoo, work, doc)
        return 4
    meta = json.loads((cache / "index.json").read_text())
    doc["cache"].update({"shape": meta["shape"], "bytes": (cache / "features.f16").stat().st_size,
                         "encoder": json.loads((cache / "encoder.json").read_text())})
    say(f"cache: {meta['shape']} float16, {(cache / 'features.f16').stat().st_size / 2**30:.2f} GiB, "
        f"{el() - t:.0f} s")

    measured: dict = {}
    for i, stage in enumerate(STAGES):
        later_core = [s for s in STAGES[i + 1:] if s in CORE]
        epochs, samples, rec = plan_stage(stage, later_core, measured)
        doc["stages"][stage] = rec
        if samples == 0:
            say(f"{stage}: skipped, too little time left ({json.dumps(rec)})")
            continue
        val_n = int(E["FORCE"].split(",")[2]) if E.get("FORCE") else VAL
        rec.update({"epochs": epochs, "samples_per_epoch": samples, "val_samples": val_n, "bf16": stage in BF16})
        say(f"{stage}: plan {epochs} x {samples}, batch {BATCH}, validation {val_n} after the last epoch "
            f"({json.dumps(rec)})")
        times: dict = {}

        def on_line(line: str, times=times, stage=stage) -> None:
            m = PROGRESS.match(line)
            if m and m.group(1) == stage:
                times.setdefault("first", el())
                times["last"], times["rate"], times["step"] = el(), float(m.group(6)), int(m.group(4))
            elif line.startswith(f"[{stage}] epoch") and "validation:" in line:
                times["val_line"] = el()

        t = el()
        extra = ["--resume", "--workers", str(WORKERS), "--epochs", str(epochs), "--samples-per-epoch", str(samples),
                 "--batch", str(BATCH), "--val-every", str(epochs), "--val-samples", str(val_n)]
        rc, stopped = run(train_cmd(data, zoo, work, stage, extra + (["--bf16"] if stage in BF16 else [])),
                          on_line=on_line)
        wall = el() - t
        exported = (zoo / ZOO_NAME / f"{stage}.pt").is_file() and rc == 0
        m = {"wall_s": round(wall, 1), "rc": rc, "stopped": stopped, "exported": exported}
        if "first" in times:
            m["startup_s"] = round(times["first"] - t, 1)
            m["rate"] = times["rate"]  # the trainer's running average over the stage's loop
            if "val_line" in times:
                loop_end = times["first"] + (epochs * (samples // BATCH) - 1) * BATCH / max(times["rate"], 1e-9)
                m["val_s"] = round(max(times["val_line"] - loop_end, 0.0), 1)
        measured[stage] = m
        rec.update(m)
        say(f"{stage}: {json.dumps(m)}")
        (OUT / "plan.json").write_text(json.dumps(doc, indent=1))
        if stopped:
            break
    collect(zoo, work, doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
