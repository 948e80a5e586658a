"""`v2vsim bench flood`: the ego's memory and scores under a flood of messages for future frames (issue 34).

    v2vsim bench flood [SCENARIO] [--frames 60] [--messages 10000] [--set KEY=VALUE ...] [--out DIR]

Runs the scenario twice through a loopback zenoh router, with the same run id and seed: once clean, once
while an attacker on the router publishes MESSAGES copies of a genuine feature message of cav1, each
rewritten to claim a frame 100 or more frames ahead (in size: exactly a real message's bytes). It prints,
for both runs, the ego's peak resident memory (metrics.json timing.peak_rss_mib), how the flood was
counted (comm.rejected_reasons) and whether every method's scores are identical, and exits 1 when the
flooded ego's peak is more than 50 MiB above the clean one or any score differs.
"""

from __future__ import annotations

import argparse
import json
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
RSS_BOUND_MIB = 50.0
RUN_ID = "flood"


def _router(endpoint: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-m", "v2vsim.cli", "router", "--listen", endpoint],
                            stderr=subprocess.PIPE, text=True)
    assert proc.stderr is not None
    if "listening" not in proc.stderr.readline():
        proc.kill()
        raise SystemExit("bench flood: the zenoh router did not start")
    return proc


def _flood(endpoint: str, messages: int, sent: list[int], stop: threading.Event) -> None:
    """Wait for a genuine cav1 feature message, then publish `messages` copies claiming frames 100+ ahead."""
    from v2vsim.comm.transport import Publisher, Subscriber, open_session
    from v2vsim.config import TransportConfig

    with open_session(TransportConfig(mode="client", connect=(endpoint,))) as session:
        sub = Subscriber(session, f"v2vsim/{RUN_ID}/features/cav1")
        genuine = None
        while genuine is None and not stop.is_set():
            got = sub.get(timeout=1)
            genuine = None if got is None else bytearray(got.data)
        if genuine is None:
            return
        frame = struct.unpack_from("<I", genuine, 12)[0]
        pub = Publisher(session, f"v2vsim/{RUN_ID}/features/cav1")
        pub.wait_matched(30)
        for i in range(messages):
            if stop.is_set():
                break
            struct.pack_into("<I", genuine, 12, frame + 100 + i)  # the codec's frame field
            pub.put(bytes(genuine))
            sent[0] += 1
        pub.close()


def run_once(scenario: str, frames: int, overrides: list[str], out: Path, endpoint: str, flood: int) -> dict:
    cmd = [sys.executable, "-m", "v2vsim.cli", "run", scenario, "--frames", str(frames), "--out", str(out),
           "--run-id", RUN_ID, "--set", "transport.mode=client", "--set", f"transport.connect=[{endpoint}]"]
    for o in overrides:
        cmd += ["--set", o]
    sent, stop = [0], threading.Event()
    attacker = threading.Thread(target=_flood, args=(endpoint, flood, sent, stop), daemon=True) if flood else None
    print(f"bench flood: {'flooded with ' + str(flood) if flood else 'clean'}: {' '.join(cmd[3:])}",
          file=sys.stderr, flush=True)
    if attacker is not None:
        attacker.start()
    proc = subprocess.Popen(cmd, cwd=REPO)
    polled = _poll_ego_rss(proc)
    rc = proc.wait()
    stop.set()
    if attacker is not None:
        attacker.join(timeout=30)
    if rc != 0:
        raise SystemExit(f"bench flood: `v2vsim run` exited with {rc}")
    metrics = json.loads((out / "metrics.json").read_text())
    return {"metrics": metrics, "sent": sent[0], "polled_rss_mib": polled[0]}


def _poll_ego_rss(proc: subprocess.Popen[bytes]) -> list[float | None]:
    """The ego process's largest RSS seen by polling every 0.1 s (psutil; None without it): the same
    measure for code whose metrics.json has no peak_rss_mib."""
    peak: list[float | None] = [None]
    try:
        import psutil
    except ImportError:
        return peak

    def poll() -> None:
        parent = psutil.Process(proc.pid)
        while proc.poll() is None:
            try:
                for c in parent.children(recursive=True):
                    if "agents.ego" in " ".join(c.cmdline()):
                        peak[0] = max(peak[0] or 0.0, c.memory_info().rss / 2**20)
            except psutil.Error:
                pass
            time.sleep(0.1)

    threading.Thread(target=poll, daemon=True).start()
    return peak


def scores(m: dict) -> dict:
    """What must not change under a flood that is refused: every method's scores and bytes, the frames."""
    return {"frames": m["frames"], "status": m["status"],
            "methods": {n: {k: v for k, v in r.items() if k != "fusion_ms"} for n, r in m["methods"].items()}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="v2vsim bench flood", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenario", nargs="?", default="intersection")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--messages", type=int, default=10_000)
    p.add_argument("--set", dest="overrides", action="append", default=[])
    p.add_argument("--out", default=None, help="keep both runs here (default: a temporary folder)")
    a = p.parse_args(argv)
    from v2vsim.comm.transport import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = _router(endpoint)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            base = Path(a.out) if a.out else Path(tmp)
            clean = run_once(a.scenario, a.frames, a.overrides, base / "clean", endpoint, 0)
            flooded = run_once(a.scenario, a.frames, a.overrides, base / "flooded", endpoint, a.messages)
    finally:
        router.send_signal(signal.SIGINT)
        router.wait(timeout=10)
    rss = {k: r["metrics"]["timing"].get("peak_rss_mib") or r["polled_rss_mib"]
           for k, r in (("clean", clean), ("flooded", flooded))}
    same = scores(clean["metrics"]) == scores(flooded["metrics"])
    print("\n| run | messages sent | frames | status | ego peak RSS (MiB) | polled RSS (MiB) | rejected |")
    print("|---|---:|---:|---|---:|---:|---|")
    for name, r in (("clean", clean), ("flooded", flooded)):
        m = r["metrics"]
        polled = "" if r["polled_rss_mib"] is None else f"{r['polled_rss_mib']:.0f}"
        print(f"| {name} | {r['sent']} | {m['frames']} | {m['status']} | {rss[name]} | {polled} | "
              f"{json.dumps(m['comm'].get('rejected_reasons', {}))} |")
    growth = (rss["flooded"] or 0) - (rss["clean"] or 0)
    print(f"\nego peak RSS flooded - clean: {growth:+.1f} MiB (bound {RSS_BOUND_MIB:g}); scores identical: {same}")
    return 0 if same and growth <= RSS_BOUND_MIB and flooded["sent"] == a.messages else 1
