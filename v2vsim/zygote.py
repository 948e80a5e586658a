"""The warm starter (issue 66): one process that has imported torch, the agents and the command line once, and forks
a fresh process for every `v2vsim run` and agent it is asked for, so that no run pays the imports again.

    python -m v2vsim.zygote SOCKET      (started by v2vsim.launch; never by hand)

What a forked process gets is what a cold `python -m MODULE ARGV` gets: its own process group, the stdin / stdout /
stderr file descriptors the requester passed (SCM_RIGHTS), the requester's environment and working directory, fresh
`random` and NumPy seeds from the OS, and MODULE's `main(ARGV)` as its whole life; it exits with main's code. The
zygote itself never runs a torch operation, opens no zenoh session and starts no Python thread, so that forking it is
safe
(v2vsim.launch checks it is single-threaded before it answers), and nothing of one run survives into the next: each
is forked from the same clean state, never reused.

Protocol (AF_UNIX SOCK_SEQPACKET, one JSON document per packet): a request {"module", "argv", "env", "cwd"} with
three file descriptors (stdin, stdout, stderr) is answered {"pid": PID} (or {"error": why}); when a process it
forked ends, the requester that asked for it gets {"exit": PID, "code": N} (N < 0: killed by signal -N, as
subprocess reports it). A requester that goes away (its connection closes: it exited or died) takes its processes
with it (SIGTERM to each one's process group, as PR_SET_PDEATHSIG does for a cold child); the zygote ends with the
process that started it.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import importlib
import importlib.util
import io
import json
import os
import random
import select
import signal
import socket
import sys
import threading
import traceback

# Imported once here, so that every forked run and agent starts with them loaded (the agents import torch).
PRELOAD = ("numpy", "torch", "zenoh", "agents.driver", "agents.cav", "agents.ego", "v2vsim.cli")
PACKET_BYTES = 1 << 20  # a request holds an environment and an argv: far below this
PR_SET_PDEATHSIG = 1
PR_SET_NAME = 15


def _threads() -> int:
    """Python threads running here. (NumPy's OpenBLAS starts a native pool at import; it re-creates it in a forked
    child itself, pthread_atfork, as every fork of a NumPy process relies on.)"""
    return threading.active_count()


def _die_with_parent() -> None:
    """SIGTERM to this process when its parent ends (Linux; elsewhere the parent's connection closing does it)."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)


def _name(name: str) -> None:
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_NAME, name.encode()[:15], 0, 0, 0)


def _send(conn: socket.socket, doc: dict) -> None:
    with contextlib.suppress(OSError):  # a requester gone meanwhile: its processes are being stopped
        conn.send(json.dumps(doc).encode())


def _child(req: dict, fds: list[int], close: list[socket.socket]) -> None:
    """The forked process: become MODULE's `main(ARGV)` as a cold start would, then exit with its code. Never
    returns (the zygote's loop lives on in the parent only)."""
    code = 1
    try:
        for s in close:
            s.close()
        os.setpgid(0, 0)
        _die_with_parent()
        _name(f"v2vsim-{req['module'].rsplit('.', 1)[-1]}")  # what `ps -o comm` and top show (the argv stays ours)
        for target, fd in zip((0, 1, 2), fds, strict=True):
            os.dup2(fd, target)
        for fd in fds:
            if fd > 2:
                os.close(fd)
        os.chdir(req["cwd"])
        os.environ.clear()
        os.environ.update(req["env"])
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        # as PYTHONUNBUFFERED=1 has them: written through, line by line
        sys.stdin = io.TextIOWrapper(io.BufferedReader(io.FileIO(0, "r", closefd=False)))
        sys.stdout = io.TextIOWrapper(io.BufferedWriter(io.FileIO(1, "w", closefd=False)), write_through=True,
                                      line_buffering=True)
        sys.stderr = io.TextIOWrapper(io.BufferedWriter(io.FileIO(2, "w", closefd=False)), write_through=True,
                                      line_buffering=True, errors="backslashreplace")
        random.seed()  # a cold process seeds these from the OS at import; forked ones would share the zygote's
        import numpy as np

        np.random.seed()
        spec = importlib.util.find_spec(req["module"])
        sys.argv = [spec.origin if spec is not None and spec.origin else req["module"], *req["argv"]]
        code = importlib.import_module(req["module"]).main(req["argv"])
        code = 0 if code is None else int(code)
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        if not isinstance(e.code, int) and e.code is not None:
            print(e.code, file=sys.stderr)
    except KeyboardInterrupt:
        code = 130
    except BaseException:  # noqa: BLE001 - a crash is the child's, reported as a cold start would
        traceback.print_exc()
        code = 1
    finally:
        with contextlib.suppress(BaseException):
            atexit._run_exitfuncs()
        with contextlib.suppress(BaseException):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code & 0xFF)


def serve(path: str) -> None:
    _die_with_parent()
    for m in PRELOAD:
        importlib.import_module(m)
    threads = _threads()
    # what a requester checks before it asks (v2vsim.launch.fits): a fork runs this interpreter with this
    # import path, whatever PYTHONPATH its request names
    with open(f"{path}.json", "w") as f:
        json.dump({"python": os.path.realpath(sys.executable), "prefix": sys.prefix,
                   "pythonpath": os.environ.get("PYTHONPATH", ""),
                   "sys_path": [os.path.realpath(p) for p in sys.path if p]}, f)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    listener.bind(path)
    listener.listen(64)
    # the starter reads this line: the zygote is ready, and single-threaded (or it must not be forked from)
    print(json.dumps({"ready": True, "threads": threads}), flush=True)
    conns: dict[socket.socket, set[int]] = {}
    owner: dict[int, socket.socket] = {}
    while True:
        readable, _, _ = select.select([listener, *conns], [], [], 0.05)
        for s in readable:
            if s is listener:
                conn, _ = listener.accept()
                conns[conn] = set()
                continue
            try:
                data, fds, _, _ = socket.recv_fds(s, PACKET_BYTES, 3)
            except OSError:
                data, fds = b"", []
            if not data:  # the requester is gone: its processes go with it
                for pid in conns.pop(s):
                    with contextlib.suppress(ProcessLookupError, PermissionError):
                        os.killpg(pid, signal.SIGTERM)
                s.close()
                continue
            try:
                req = json.loads(data)
                if len(fds) != 3:
                    raise ValueError(f"expected 3 file descriptors, got {len(fds)}")
                pid = os.fork()
            except (ValueError, OSError) as e:
                for fd in fds:
                    os.close(fd)
                _send(s, {"error": f"{type(e).__name__}: {e}"})
                continue
            if pid == 0:
                _child(req, fds, [listener, *conns])
            for fd in fds:
                os.close(fd)
            conns[s].add(pid)
            owner[pid] = s
            _send(s, {"pid": pid})
        while owner:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                break
            if pid == 0:
                break
            conn = owner.pop(pid, None)
            if conn is not None and conn in conns:
                conns[conn].discard(pid)
                _send(conn, {"exit": pid, "code": os.waitstatus_to_exitcode(status)})


if __name__ == "__main__":
    serve(sys.argv[1])
