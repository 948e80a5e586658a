"""Benchmark the comm layer on loopback: codec cost, zenoh round trip and throughput, frame share.

    v2vsim bench comm [--reps 200] [--json out.json]

Two processes (this one and an echo/sink child), each with its own zenoh peer session on
tcp/127.0.0.1, as the agents run. For each message size it compares bare zenoh carrying raw
bytes of the encoded message's size with the v2vsim path (codec encode -> Publisher ->
Subscriber queue -> codec decode). Not a test: figures depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable

import numpy as np
import zenoh

from v2vsim.comm import codec
from v2vsim.comm import transport as T
from v2vsim.comm.identity import issue
from v2vsim.config import TransportConfig

SHAPES = {"feat64": (64, 32, 32), "feat128": (128, 32, 32)}
FRAME_S = 0.1


def _msg(shape: tuple[int, ...], frame: int = 0, compression: str = "none",
         dtype: type = np.float16) -> codec.Message:
    """A feature message with post-ReLU statistics (about half zeros), like an encoder's output.

    float16 by default: the encoder hands over `.half()` output; from float32 the codec casts
    with numpy, which costs more than the rest of encode (see encode_f32_ms).
    """
    rng = np.random.default_rng(frame)
    feats = np.maximum(rng.standard_normal(shape), 0).astype(dtype)
    return codec.Message("features", "bench", "cav1", frame, frame * FRAME_S, (1.0, 2.0, 0.0, 0.3),
                         feats, compression=compression)  # type: ignore[arg-type]


def _timeit(fn: Callable[[], object], reps: int) -> float:
    """Median milliseconds of fn over reps calls (after a warm-up call)."""
    fn()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts) * 1000


# ---- the child: echo and sink ----------------------------------------------------------------


def _open(port: int | None, shm: bool, peers: list[str] | None = None) -> zenoh.Session:
    cfg = T.zenoh_config(TransportConfig(), port, peers=peers or [])
    cfg.insert_json5("transport/shared_memory/enabled", json.dumps(shm))
    return zenoh.open(cfg)


def child(port: int, shm: bool) -> None:
    """Echo bench/ping/<mode> to bench/pong/<mode>; count bench/tput/<mode>, answer on an 'E' marker."""
    session = _open(None, shm, [T.loopback_endpoint(port)])
    pongs = {mode: session.declare_publisher(f"bench/pong/{mode}", express=True,
                                             congestion_control=zenoh.CongestionControl.BLOCK)
             for mode in ("raw", "v2v")}
    done = session.declare_publisher("bench/done", congestion_control=zenoh.CongestionControl.BLOCK)
    counts = {"raw": 0, "v2v": 0}

    def on_ping(sample: zenoh.Sample) -> None:
        pongs[str(sample.key_expr).rsplit("/", 1)[-1]].put(sample.payload)

    def on_tput(sample: zenoh.Sample) -> None:
        mode = str(sample.key_expr).rsplit("/", 1)[-1]
        data = sample.payload.to_bytes()
        if data == b"E":
            done.put(str(counts[mode]).encode())
            counts[mode] = 0
            return
        if mode == "v2v":
            codec.decode(data, known_senders={"cav1"})
        counts[mode] += 1

    session.declare_subscriber("bench/ping/*", on_ping)
    session.declare_subscriber("bench/tput/*", on_tput)
    print("READY", flush=True)
    sys.stdin.readline()  # the parent closes stdin when it is done
    session.close()


# ---- the parent ------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="v2vsim bench comm", description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--json", default=None)
    ap.add_argument("--no-shm", action="store_true",
                    help="turn off zenoh's same-host shared-memory path (what agents on different hosts get)")
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        child(args.child, not args.no_shm)
        return

    results: dict[str, dict[str, float]] = {}
    key = os.urandom(32)
    ids = issue("bench", ["cav.cav1", "ego.cav0"])  # comm.auth.identity per_process
    for name, shape in SHAPES.items():
        m = _msg(shape)
        data = codec.encode(m)
        signed = codec.encode(m, key)
        by_cav1 = codec.encode(m, ids["cav.cav1"])
        zm, m32 = _msg(shape, compression="zlib"), _msg(shape, dtype=np.float32)
        zdata = codec.encode(zm)
        results[name] = {
            "bytes": len(data),
            "bytes_zlib": len(zdata),
            "encode_ms": _timeit(lambda m=m: codec.encode(m), args.reps),
            "encode_f32_ms": _timeit(lambda m=m32: codec.encode(m), args.reps),
            "decode_ms": _timeit(lambda d=data: codec.decode(d, known_senders={"cav1"}), args.reps),
            "encode_hmac_ms": _timeit(lambda m=m: codec.encode(m, key), args.reps),
            "decode_hmac_ms": _timeit(lambda d=signed: codec.decode(d, key=key), args.reps),
            "encode_ed25519_ms": _timeit(lambda m=m: codec.encode(m, ids["cav.cav1"]), args.reps),
            "decode_ed25519_ms": _timeit(lambda d=by_cav1: codec.decode(d, key=ids["ego.cav0"]), args.reps),
            "arrival_ed25519_ms": _timeit(lambda d=by_cav1: codec.check_arrival(d, key=ids["ego.cav0"]), args.reps),
            "encode_zlib_ms": _timeit(lambda m=zm: codec.encode(m), args.reps // 4),
            "decode_zlib_ms": _timeit(lambda d=zdata: codec.decode(d), args.reps // 4),
        }

    port = T.free_port()
    session = _open(port, not args.no_shm)
    cmd = [sys.executable, "-m", "v2vsim.bench.comm", "--child", str(port)] + (["--no-shm"] if args.no_shm else [])
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "READY"
        # bare zenoh: its own publisher and FIFO-channel subscriber, raw bytes
        ping = session.declare_publisher("bench/ping/raw", congestion_control=zenoh.CongestionControl.BLOCK,
                                         express=True)
        bare_pong = session.declare_subscriber("bench/pong/raw")
        # v2vsim: codec + the transport wrappers (callback -> queue.Queue)
        v2v_ping = T.Publisher(session, "bench/ping/v2v")
        v2v_pong = T.Subscriber(session, "bench/pong/v2v")
        tput = {"raw": session.declare_publisher("bench/tput/raw", congestion_control=zenoh.CongestionControl.BLOCK),
                "v2v": T.Publisher(session, "bench/tput/v2v", express=False)}
        done = session.declare_subscriber("bench/done")
        deadline = time.monotonic() + 15
        pubs = [ping, tput["raw"]]
        while not (all(p.matching_status.matching for p in pubs) and v2v_ping.matched() and tput["v2v"].matched()):
            if time.monotonic() > deadline:
                raise RuntimeError("the echo process never matched")
            time.sleep(0.01)

        def rtt_bare(payload: bytes) -> None:
            ping.put(payload)
            bare_pong.recv()

        def rtt_v2v(msg: codec.Message) -> None:
            v2v_ping.put(codec.encode(msg))
            got = v2v_pong.get(timeout=10)
            assert got is not None
            codec.decode(got.data, known_senders={"cav1"})

        results["small"] = {"bytes": 64, "rtt_bare_ms": _timeit(lambda: rtt_bare(b"x" * 64), args.reps)}
        for name, shape in SHAPES.items():
            r = results[name]
            raw = os.urandom(int(r["bytes"]))
            msg = _msg(shape)
            r["rtt_bare_ms"] = _timeit(lambda raw=raw: rtt_bare(raw), args.reps)
            r["rtt_v2v_ms"] = _timeit(lambda msg=msg: rtt_v2v(msg), args.reps)
            n = max(500, 5 * args.reps)
            msgs = [_msg(shape, i) for i in range(4)]
            for mode in ("raw", "v2v"):
                t0 = time.perf_counter()
                for i in range(n):
                    tput[mode].put(raw if mode == "raw" else codec.encode(msgs[i % 4]))
                tput[mode].put(b"E")
                count = int(done.recv().payload.to_string())
                dt = time.perf_counter() - t0
                assert count == n, (count, n)
                r[f"tput_{mode}_msgs_s"] = n / dt
                r[f"tput_{mode}_MBps"] = n * r["bytes"] / dt / 1e6
            one_way = r["rtt_v2v_ms"] / 2
            r["one_way_v2v_ms"] = one_way
            r["frame_share_1msg"] = one_way / (FRAME_S * 1000)
            # an ego fusing 3 CAVs: each CAV encodes in its own process, the ego decodes all three
            r["frame_share_ego_3cavs"] = (r["encode_ms"] + r["rtt_bare_ms"] / 2 + 3 * r["decode_ms"]) / (FRAME_S * 1000)
    finally:
        if proc.stdin:
            proc.stdin.close()
        proc.wait(timeout=10)
        session.close()

    print(f"{'':8} {'bytes':>8} {'enc ms':>7} {'enc f32':>7} {'dec ms':>7} {'enc+hmac':>8} "
          f"{'dec+hmac':>8} {'enc+ed':>7} {'dec+ed':>7} {'arr ed':>7} {'zlib B':>8} {'enc zlib':>8} {'dec zlib':>8}")
    for name in SHAPES:
        r = results[name]
        print(f"{name:8} {r['bytes']:8.0f} {r['encode_ms']:7.3f} {r['encode_f32_ms']:7.3f} {r['decode_ms']:7.3f} "
              f"{r['encode_hmac_ms']:8.3f} {r['decode_hmac_ms']:8.3f} {r['encode_ed25519_ms']:7.3f} "
              f"{r['decode_ed25519_ms']:7.3f} {r['arrival_ed25519_ms']:7.3f} {r['bytes_zlib']:8.0f} "
              f"{r['encode_zlib_ms']:8.3f} {r['decode_zlib_ms']:8.3f}")
    print("(+ed: signed by the sending process's Ed25519 key, comm.auth.identity per_process; arr ed: the check on "
          "arrival, signature included)")
    print(f"\nzenoh shared memory: {'off' if args.no_shm else 'on (same-host default)'}")
    print(f"round trip, 64 B bare zenoh: {results['small']['rtt_bare_ms']:.3f} ms (median)")
    print(f"{'':8} {'rtt bare':>9} {'rtt v2v':>9} {'MB/s bare':>10} {'MB/s v2v':>9} {'msg/s bare':>10} "
          f"{'msg/s v2v':>9} {'1-way v2v':>9} {'% frame':>8} {'% ego 3cav':>10}")
    for name in SHAPES:
        r = results[name]
        print(f"{name:8} {r['rtt_bare_ms']:9.3f} {r['rtt_v2v_ms']:9.3f} {r['tput_raw_MBps']:10.1f} "
              f"{r['tput_v2v_MBps']:9.1f} {r['tput_raw_msgs_s']:10.0f} {r['tput_v2v_msgs_s']:9.0f} "
              f"{r['one_way_v2v_ms']:9.3f} {100 * r['frame_share_1msg']:8.2f} {100 * r['frame_share_ego_3cavs']:10.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)
    return 0


if __name__ == "__main__":
    threading.current_thread().name = "bench"
    raise SystemExit(main())
