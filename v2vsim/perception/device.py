"""Where a process's models run (`perception.device`: auto | cpu | cuda | cuda:N), and what a run says about it.

Every process that infers (the CAV agents, the egos, `v2vsim evaluate`) resolves the key on its own host, moves
its models there once, and the inference functions (v2vsim.perception.encode, .fuse, .extrapolate, .build's
compress / decompress) move their inputs to the device their model sits on (`model_device`) and bring what they
return back to the host as numpy: what goes on the wire and what is scored is the same float32 on every device.
On the CPU, `Tensor.to(cpu)` and `.cpu()` return the tensor itself, so that path makes no copy and computes
exactly what it did before the key existed.

The scenario loader imports no torch, so the schema only checks the spelling; whether this host has the device
asked for is checked here, by the runner before any process starts (check_scenario) and again in each agent.
"""

from __future__ import annotations

import itertools
import os
import platform
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from v2vsim.config import ConfigError
from v2vsim.config.schema_perception import DEVICE_PATTERN


def resolve_device(asked: str) -> torch.device:
    """'auto' -> the current CUDA device when torch sees one, else the CPU; 'cpu'; 'cuda' -> the current CUDA
    device; 'cuda:N' -> that one. ConfigError (one line naming perception.device, what was asked and what this
    host has) for a CUDA device this host does not have, or a spelling the key does not allow."""
    if not DEVICE_PATTERN.fullmatch(asked):
        raise ConfigError(f"perception.device: {asked!r}: allowed: auto, cpu, cuda, cuda:N")
    if asked == "cpu":
        return torch.device("cpu")
    available = torch.cuda.is_available()
    if asked == "auto":
        return torch.device("cuda", torch.cuda.current_device()) if available else torch.device("cpu")
    if not available:
        raise ConfigError(f"perception.device: {asked!r} asked, but this host has no CUDA device ({_cuda_build()}); "
                          "allowed here: auto (which runs on the CPU) or cpu")
    index = torch.cuda.current_device() if asked == "cuda" else int(asked.split(":")[1])
    count = torch.cuda.device_count()
    if index >= count:
        raise ConfigError(f"perception.device: {asked!r} asked, but this host has {count} CUDA device"
                          f"{'' if count == 1 else 's'} (cuda:0..cuda:{count - 1}); allowed here: auto, cpu, cuda, "
                          f"cuda:0..cuda:{count - 1}")
    return torch.device("cuda", index)


def _cuda_build() -> str:
    """Why torch sees no CUDA device, as far as it can tell: a CPU-only build, or no driver / GPU."""
    if torch.version.cuda is None:
        return f"torch {torch.__version__} is a CPU-only build"
    return f"torch {torch.__version__} is built for CUDA {torch.version.cuda} but finds no GPU or driver"


def prepare(device: torch.device) -> None:
    """Make inference on `device` repeatable where torch allows, and float32 mean float32 (docs/run.md "Running on
    a GPU"); nothing on the CPU, whose path stays as it was. cuDNN picks its convolution algorithms by timing them
    unless told not to, and the pick can differ from run to run; deterministic algorithms where they exist, a
    warning (not an error) for an op that has none, so that a run never stops over it. cuBLAS needs its
    workspace fixed before its first call for deterministic results (setdefault: a user's own setting wins).
    cuDNN convolutions would run in TF32 (10-bit mantissa) by default: IEEE float32 instead, so that
    `perception.precision: fp32` is what it says on every device (bf16 is the way to trade accuracy for speed)."""
    if device.type != "cuda":
        return
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.backends.cudnn.benchmark = False
    torch.backends.cudnn.deterministic = True
    torch.backends.cudnn.conv.fp32_precision = "ieee"  # the new API only: mixing it with allow_tf32 is an error
    torch.backends.cuda.matmul.fp32_precision = "ieee"
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.cuda.set_device(device)


def model_device(module: nn.Module) -> torch.device:
    """The device `module`'s weights sit on (its first parameter or buffer); the CPU for a module without any."""
    first = next(itertools.chain(module.parameters(), module.buffers()), None)
    return torch.device("cpu") if first is None else first.device


def to_host(t: Tensor) -> np.ndarray:
    """A tensor as numpy on the host: copied off a GPU; on the CPU the tensor's own memory, as before."""
    return t.cpu().numpy()


def device_name(device: torch.device) -> str:
    """The GPU's name as CUDA reports it, or the CPU's model name."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return cpu_name()


def cpu_name() -> str:
    """The CPU's model name (Linux: /proc/cpuinfo), else what the platform module says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "cpu"


def device_record(asked: str, used: torch.device) -> dict[str, str]:
    """metrics.json `device`: what was asked, what ran ("cpu" or "cuda:N") and that device's name."""
    return {"asked": asked, "used": str(used), "name": device_name(used)}


def device_line(record: dict[str, str]) -> str:
    """report.md's line on where the models ran; under auto without a GPU it says the CPU was the fallback."""
    asked, used, name = record["asked"], record["used"], record["name"]
    line = f"Inference device: {used} ({name}), `perception.device: {asked}`"
    if asked == "auto" and used == "cpu":
        return line + ": torch saw no CUDA device on this host, so auto ran on the CPU."
    return line + "."
