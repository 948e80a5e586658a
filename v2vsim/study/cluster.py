"""A sweep's runs on a Dask distributed cluster: `v2vsim sweep ... --engine dask --scheduler tcp://HOST:8786`.

Why Dask distributed rather than Ray: it is pure Python (`pip install -e ".[cluster]"`), a cluster is two
commands that start in about a second (`dask scheduler` on one machine, `dask worker tcp://HOST:8786
--nthreads 1` on each), and a task here is only "run one child process and hand back its files", which
needs none of Ray's object store, raylet and dashboard daemons, heavy on 2-core machines.

One run is one task. The worker runs `v2vsim run` as a child process in a scratch directory and returns
its exit code and every file the run wrote (plus the run's log); the sweep writes them into
DIR/runs/<point>/seed<k>/, exactly where the local engine puts them, so everything after (resuming,
sweep.csv, statistics, plots) is the same code. Workers need v2vsim installed, and the scenario and the
files it names (the SUMO network, weights) at the same absolute path as on the sweep's machine: a
shared or identical checkout. Ctrl-C sets a Dask Event the task polls; the task then stops its run with
SIGINT as the local engine does (partial results come back), and SIGKILL after STOP_GRACE_S.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

from v2vsim.config import ConfigError
from v2vsim.study.plan import RunSpec
from v2vsim.study.runs import LOG, STOP_GRACE_S

SCRATCH_OUT = "run"  # the run's --out inside the task's scratch directory
CONNECT_TIMEOUT_S = 10.0  # how long --scheduler may take to answer (Dask retries a refused connection until then)


def connect(address: str) -> Any:
    """A Dask client for the scheduler at `address`; ConfigError with the reason when there is none."""
    try:
        from distributed import Client
    except ImportError:
        raise ConfigError("--engine dask: the 'distributed' package is not installed; "
                          "pip install -e \".[cluster]\"") from None
    try:
        return Client(address, timeout=f"{CONNECT_TIMEOUT_S:g}s", set_as_default=False)
    except (OSError, TimeoutError) as e:
        raise ConfigError(f"--scheduler {address}: no Dask scheduler answered ({e})") from None


def worker_threads(client: Any) -> int:
    """Tasks the cluster runs at once (the sweep's default --jobs under dask)."""
    return max(1, sum(client.nthreads().values()))


def run_task(argv: list[str], stop_event: str, poll_s: float = 0.5) -> tuple[int, dict[str, bytes]]:
    """On a worker: run `python -m v2vsim.cli run ...` (argv with --out SCRATCH_OUT) in a scratch
    directory; (exit code, {relative path: bytes} of what it wrote, LOG included)."""
    from distributed import Event

    stop = Event(stop_event)
    with tempfile.TemporaryDirectory(prefix="v2vsim-sweep-") as tmp:
        work = Path(tmp)
        with open(work / LOG, "wb") as log:
            proc = subprocess.Popen([sys.executable, *argv], cwd=work, stdin=subprocess.DEVNULL, stdout=log,
                                    stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"),
                                    process_group=0)
            stopped_at = None
            while proc.poll() is None:
                if stopped_at is None and stop.wait(timeout=poll_s):
                    stopped_at = time.monotonic()
                    _signal(proc, signal.SIGINT)  # the run writes partial results and exits 130
                elif stopped_at is not None:
                    if time.monotonic() - stopped_at > STOP_GRACE_S:
                        _signal(proc, signal.SIGKILL)
                    time.sleep(poll_s)
        files = {LOG: (work / LOG).read_bytes()}
        out = work / SCRATCH_OUT
        if out.is_dir():
            files.update({str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()})
        return proc.returncode, files


def _signal(proc: subprocess.Popen, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, sig)


class DaskJob:
    """One run submitted to the cluster (the `Job` protocol of v2vsim.study.runs)."""

    def __init__(self, client: Any, spec: RunSpec, scenario: Path) -> None:
        from distributed import Event

        self.spec = spec
        self.code: int | None = None
        name = f"v2vsim-stop-{uuid.uuid4().hex}"
        self._stop = Event(name, client=client)
        argv = spec.argv(scenario, out=Path(SCRATCH_OUT))
        self.future = client.submit(run_task, argv, name, key=f"v2vsim-run-{spec.out.name}-{uuid.uuid4().hex[:8]}",
                                    pure=False)

    def poll(self) -> int | None:
        if self.code is not None or not self.future.done():
            return self.code
        try:
            code, files = self.future.result()
        except Exception as e:  # noqa: BLE001 - the worker died, or the task raised: the run failed, say why
            self.spec.out.mkdir(parents=True, exist_ok=True)
            (self.spec.out / LOG).write_text(f"v2vsim sweep: the Dask task failed: {type(e).__name__}: {e}\n")
            self.code = 1
            return self.code
        for rel, data in files.items():
            path = self.spec.out / rel
            if not path.resolve().is_relative_to(self.spec.out.resolve()):
                continue  # a path from the worker that would leave the run directory: ignored
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        self.code = code
        return code

    def interrupt(self) -> None:
        self._stop.set()

    def kill(self) -> None:
        self.future.cancel()
        if self.code is None:
            self.code = -int(signal.SIGKILL)
