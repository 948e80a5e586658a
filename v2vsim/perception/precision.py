"""Inference precision (`perception.precision`): float32, or bfloat16 autocast where the CPU computes it natively.

bfloat16 keeps float32's exponent and 8 bits of mantissa, so activations neither overflow nor underflow; on a CPU
with AMX tiles (Sapphire Rapids and later) or AVX-512 BF16 the matrix products and convolutions run at about
twice float32's rate, measured in `v2vsim bench models` and docs/results.md. Autocast covers the models only (the
encoder, fusion and heads): every tensor that leaves a model is cast back to float32 before it is decoded,
scored or put on the wire, so boxes, maps and messages have the same types either way. What it changes in the
scores is measured, not assumed: docs/results.md "Inference in bfloat16".
"""

from __future__ import annotations

import contextlib
from typing import Literal

import torch

Precision = Literal["fp32", "bf16"]


def native_bf16() -> bool:
    """Whether this CPU has native bfloat16 matrix units (AMX tiles or AVX-512 BF16)."""
    cpu = torch.cpu
    try:
        return bool(cpu._is_amx_tile_supported() or cpu._is_avx512_bf16_supported())
    except AttributeError:  # an older torch without the probes: assume not
        return False


def resolve(asked: str) -> Precision:
    """'auto' -> 'bf16' where native_bf16(), else 'fp32'; 'fp32' and 'bf16' as asked."""
    if asked == "auto":
        return "bf16" if native_bf16() else "fp32"
    if asked not in ("fp32", "bf16"):
        raise ValueError(f"precision {asked!r}: allowed: auto, fp32, bf16")
    return asked  # type: ignore[return-value]


def autocast(precision: Precision, device_type: str = "cpu") -> contextlib.AbstractContextManager:
    """The context a model's forward pass runs in: bfloat16 autocast on the device type the model sits on ("cpu"
    or "cuda": an autocast for the other type would leave the model's ops in float32), or nothing."""
    if precision == "bf16":
        return torch.autocast(device_type, dtype=torch.bfloat16)
    return contextlib.nullcontext()
