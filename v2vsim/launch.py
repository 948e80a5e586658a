"""How the harness starts its processes (`v2vsim run`'s agents, a sweep's or benchmark's runs): forked from a warm
starter (v2vsim.zygote) that imported torch and the agents once, or cold, `python -m MODULE ARGV`.

    V2VSIM_START=warm (default on Linux) | cold
    V2VSIM_ZYGOTE=SOCKET      set by whoever started the zygote: the processes it starts use the same one

Either way a process starts in its own process group, with the environment, stdin and stdout it is given, ends with
its parent (PR_SET_PDEATHSIG cold; the zygote stops the processes of a requester that goes away warm) and runs
exactly what a cold start runs: forked from the same clean state each time, never reused, so that a run's results
are the same to the last digit (tests/v2vsim/test_launch.py compares a warm run with a cold one). What a warm start
saves is the interpreter and the imports (torch alone: about 2 s of CPU per process here).
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from v2vsim.config import ConfigError

MODE_ENV = "V2VSIM_START"
ZYGOTE_ENV = "V2VSIM_ZYGOTE"
MODES = ("warm", "cold")
READY_TIMEOUT_S = 120.0  # the zygote's imports on a loaded 2-core machine
PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def start_mode(env: Mapping[str, str] | None = None) -> str:
    """V2VSIM_START: warm (the default on Linux) or cold; ConfigError for another value."""
    env = os.environ if env is None else env
    mode = env.get(MODE_ENV, "warm" if sys.platform.startswith("linux") else "cold") or "warm"
    if mode not in MODES:
        raise ConfigError(f"{MODE_ENV}={mode!r}: allowed: {', '.join(MODES)}")
    return "cold" if not sys.platform.startswith("linux") else mode


def die_with_parent(parent: int) -> Callable[[], None] | None:
    """What a cold child runs between fork and exec: ask Linux for SIGTERM when its parent dies.

    PR_SET_PDEATHSIG fires when the thread that forked the child ends, so children are started from the main
    thread only, before any reader thread of theirs exists.
    """
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    sigterm = int(signal.SIGTERM)

    def setup() -> None:
        prctl(PR_SET_PDEATHSIG, sigterm, 0, 0, 0)
        if os.getppid() != parent:  # the parent died before prctl took effect
            os.kill(os.getpid(), sigterm)

    return setup


class Zygote:
    """A warm starter this process started and owns (it ends with this process, or at `close`). It imports in
    the background: `wait_ready` blocks until it answers (a runner checks its scenario meanwhile)."""

    def __init__(self) -> None:
        self._dir = tempfile.TemporaryDirectory(prefix="v2vsim-zygote-")
        self.path = str(Path(self._dir.name) / "socket")
        self.proc = subprocess.Popen([sys.executable, "-m", "v2vsim.zygote", self.path], stdin=subprocess.DEVNULL,
                                     stdout=subprocess.PIPE, process_group=0,
                                     preexec_fn=die_with_parent(os.getpid()))
        self._ready = False

    def wait_ready(self) -> None:
        """Block until the zygote has imported and listens; RuntimeError (naming the way out) if it cannot."""
        if self._ready:
            return
        assert self.proc.stdout is not None
        line = _read_line(self.proc.stdout, READY_TIMEOUT_S)
        try:
            doc = json.loads(line)
        except ValueError:
            doc = {}
        if not doc.get("ready"):
            self.close()
            raise RuntimeError(f"the warm starter (v2vsim.zygote) did not start: {line.strip()!r}; "
                               f"{MODE_ENV}=cold starts every process cold")
        if doc.get("threads", 1) != 1:  # forking a process with threads would copy their locks, held
            self.close()
            raise RuntimeError(f"the warm starter has {doc['threads']} threads after its imports; it must have "
                               f"one to be forked from ({MODE_ENV}=cold starts every process cold)")
        self._ready = True

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(timeout=5)
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._dir.cleanup()

    def __enter__(self) -> Zygote:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _read_line(stream: IO[bytes], timeout_s: float) -> str:
    got: queue.Queue[bytes] = queue.Queue()
    threading.Thread(target=lambda: got.put(stream.readline()), daemon=True).start()
    try:
        return got.get(timeout=timeout_s).decode(errors="replace")
    except queue.Empty:
        return f"(nothing within {timeout_s:g} s)"


@dataclass
class Forked:
    """A process the zygote forked for this one: what the harness uses of subprocess.Popen."""

    pid: int
    stdin: IO[bytes] | None
    stdout: IO[bytes] | None
    _ended: threading.Event = field(default_factory=threading.Event)
    returncode: int | None = None

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if not self._ended.wait(timeout):
            raise subprocess.TimeoutExpired(f"pid {self.pid}", timeout or 0.0)
        assert self.returncode is not None
        return self.returncode

    def _exited(self, code: int) -> None:
        self.returncode = code
        self._ended.set()


class Client:
    """This process's connection to a zygote: asks it for processes and hears when they end."""

    def __init__(self, path: str) -> None:
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._sock.connect(path)
        self._replies: queue.Queue[dict] = queue.Queue()
        self._procs: dict[int, Forked] = {}
        self._early: dict[int, int] = {}  # exits heard before their request's answer was handled
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, name="zygote-client", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while True:
            try:
                data = self._sock.recv(1 << 16)
            except OSError:
                data = b""
            if not data:  # the zygote is gone: so are the processes it forked (they die with it)
                with self._lock:
                    for p in self._procs.values():
                        if p.returncode is None:
                            p._exited(-int(signal.SIGTERM))
                self._replies.put({"error": "the warm starter (v2vsim.zygote) ended"})
                return
            doc = json.loads(data)
            if "exit" in doc:
                with self._lock:
                    p = self._procs.get(doc["exit"])
                    if p is None:
                        self._early[doc["exit"]] = doc["code"]
                    else:
                        p._exited(doc["code"])
            else:
                self._replies.put(doc)

    def start(self, module: str, argv: list[str], env: Mapping[str, str], *, stdin_pipe: bool,
              stdout: IO[bytes] | None) -> Forked:
        """Fork `python -m module argv` from the zygote: stdin a pipe (Forked.stdin) or /dev/null; stdout and
        stderr into `stdout` (a file), or into a pipe (Forked.stdout) when it is None."""
        mine: list[int] = []  # this process's ends, kept
        theirs: list[int] = []  # the child's ends, passed and closed here
        try:
            if stdin_pipe:
                r, w = os.pipe()
                theirs.append(r)
                mine.append(w)
            else:
                theirs.append(os.open(os.devnull, os.O_RDONLY))
            if stdout is None:
                r, w = os.pipe()
                mine.append(r)
                out_fd = w
                theirs += [w, w]
            else:
                out_fd = stdout.fileno()
                theirs += [out_fd, out_fd]
            req = {"module": module, "argv": list(argv), "env": dict(env), "cwd": os.getcwd()}
            socket.send_fds(self._sock, [json.dumps(req).encode()], theirs)
            reply = self._replies.get()
        finally:
            for fd in {*theirs} - ({stdout.fileno()} if stdout is not None else set()):
                os.close(fd)
        if "pid" not in reply:
            for fd in mine:
                os.close(fd)
            raise RuntimeError(f"the warm starter could not start {module}: {reply.get('error')}")
        proc = Forked(reply["pid"], os.fdopen(mine[0], "wb") if stdin_pipe else None,
                      os.fdopen(mine[-1], "rb") if stdout is None else None)
        with self._lock:
            self._procs[proc.pid] = proc
            if proc.pid in self._early:
                proc._exited(self._early.pop(proc.pid))
        return proc

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._sock.close()


Process = subprocess.Popen[bytes] | Forked


@dataclass
class Launcher:
    """Starts this process's children: warm, forked by the zygote at `path` (one this launcher started and owns,
    or one named by V2VSIM_ZYGOTE), or cold when `path` is None."""

    path: str | None = None
    owned: Zygote | None = None
    _client: Client | None = None
    _identity: dict[str, Any] | None = None

    @property
    def warm(self) -> bool:
        return self.path is not None

    def _fits(self, env: Mapping[str, str]) -> bool:
        """Whether a process with environment `env` may be forked by this launcher's zygote (`fits`: a fork keeps
        the zygote's interpreter and import path, whatever the request's environment says)."""
        if self._identity is None:
            if self.owned is not None:
                self.owned.wait_ready()
            self._identity = zygote_identity(self.path) if self.path is not None else {}
        return fits(self._identity, env)

    def child_env(self, env: Mapping[str, str]) -> dict[str, str]:
        """`env` for a child that starts processes of its own (a sweep's run): the same zygote for them."""
        return {**env, ZYGOTE_ENV: self.path} if self.path is not None else dict(env)

    def start(self, module: str, argv: list[str], env: Mapping[str, str], *, stdin_pipe: bool = False,
              stdout: IO[bytes] | None = None) -> Process:
        """`python -m module argv` in its own process group, stdout and stderr into `stdout` (a file) or a pipe
        (the process's .stdout) when None, stdin a pipe (.stdin) or /dev/null. Cold where the zygote does not fit
        `env` (another PYTHONPATH)."""
        if self.path is None or not self._fits(env):
            return subprocess.Popen([sys.executable, "-m", module, *argv], env=dict(env),
                                    stdin=subprocess.PIPE if stdin_pipe else subprocess.DEVNULL,
                                    stdout=subprocess.PIPE if stdout is None else stdout, stderr=subprocess.STDOUT,
                                    process_group=0, preexec_fn=die_with_parent(os.getpid()))
        if self._client is None:
            if self.owned is not None:
                self.owned.wait_ready()
            self._client = Client(self.path)
        return self._client.start(module, argv, env, stdin_pipe=stdin_pipe, stdout=stdout)

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
        if self.owned is not None:
            self.owned.close()

    def __enter__(self) -> Launcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def zygote_identity(path: str) -> dict[str, Any]:
    """The interpreter, prefix and import path of the zygote at socket `path` (written beside it before it listens; {}
    where it cannot be read: such a zygote fits nothing)."""
    try:
        with open(f"{path}.json") as f:
            doc = json.load(f)
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def _entries(pythonpath: str) -> set[str]:
    return {os.path.realpath(p) for p in pythonpath.split(os.pathsep) if p}


def fits(identity: Mapping[str, Any], env: Mapping[str, str]) -> bool:
    """Whether a fork of the zygote with this identity runs what `python -m` would with environment `env`: the
    same interpreter and prefix (a venv's python needs its own starter), every PYTHONPATH entry of `env` on the
    zygote's import path, and none of the zygote's own PYTHONPATH entries missing from `env`'s (a plugin's)."""
    wanted = _entries(env.get("PYTHONPATH", ""))
    return (identity.get("python") == os.path.realpath(sys.executable)
            and identity.get("prefix") == sys.prefix  # a venv's python resolves to its base interpreter's
            and wanted <= set(identity.get("sys_path", ()))
            and _entries(identity.get("pythonpath", "")) <= wanted)


def launcher(env: Mapping[str, str] | None = None) -> Launcher:
    """The launcher of this process's children: the zygote named by V2VSIM_ZYGOTE when one is up (a sweep's) and
    it fits this process (`fits`), else one of its own when V2VSIM_START is warm (it starts importing now), else
    cold."""
    env = os.environ if env is None else env
    if start_mode(env) == "cold":
        return Launcher()
    path = env.get(ZYGOTE_ENV)
    if path and Path(path).exists() and fits(zygote_identity(path), env):
        return Launcher(path)
    z = Zygote()
    return Launcher(z.path, owned=z)
