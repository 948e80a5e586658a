"""The fusion contract (models.fusion.base), checked on a module: what every fusion method registered from
outside the package (an entry point in group "v2vsim.fusion", or models.registry.register_fusion) must pass
before anything builds it.

check_fusion_module(name, factory) instantiates ``factory(channels, **kwargs)`` at a small size (the tiny
preset's channels on a 16 x 16 grid) and feeds it a seeded random batch:

- it is an ``nn.Module`` whose forward(features [B, L, C, H, W], valid_mask [B, L] bool) returns a tensor
  [B, C, H, W] of the features' dtype, with finite values, for several agents and for the ego alone (L = 1);
- an absent agent (valid_mask False) is ignored exactly: other features in its slots, and NaN / inf there,
  leave the output bit-for-bit unchanged.

A failure raises models.registration.PluginError naming the method, where it comes from and what it broke. The check
runs in inference mode, under torch.no_grad, on the CPU, and leaves the global random state as it found it (a
seeded run builds the same weights whether or not a plugin was checked first).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor, nn

from models.registration import PluginError

CHECK_CHANNELS = 64  # the tiny preset's C
CHECK_CELLS = 16
# [B = 3, L = 4]: slot 0 (the ego) always valid; absent agents between and after present ones; an ego alone
CHECK_MASK = ((True, True, False, True), (True, False, False, False), (True, True, True, False))
CONTRACT = "models/fusion/base.py"


def _describe(x: object) -> str:
    if isinstance(x, Tensor):
        return f"a {str(x.dtype).removeprefix('torch.')} tensor of shape {tuple(x.shape)}"
    return f"a {type(x).__name__}"


def check_fusion_module(name: str, module_factory: Callable[..., Any], *, where: str = "",
                        kwargs: dict[str, Any] | None = None, channels: int = CHECK_CHANNELS) -> None:
    """Raise PluginError unless `module_factory(channels, **kwargs)` keeps the fusion contract (module docstring).
    `where`: where the method comes from (an entry point and the object it points at), put in the message."""
    label = f"fusion method {name!r}" + (f" ({where})" if where else "")

    def fail(what: str) -> PluginError:
        return PluginError(f"{label}: {what} (the fusion contract: {CONTRACT})")

    kwargs = dict(kwargs or {})
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        try:
            module = module_factory(channels, **kwargs)
        except Exception as e:  # noqa: BLE001 - any failure of third-party code is reported, not raised through
            args = ", ".join([str(channels), *(f"{k}={v!r}" for k, v in kwargs.items())])
            raise fail(f"cannot be built as {getattr(module_factory, '__name__', 'factory')}({args}): "
                       f"{type(e).__name__}: {_one_line(e)}") from None
        if not isinstance(module, nn.Module):
            raise fail(f"building it gave {_describe(module)}, not a torch.nn.Module")
        module = module.eval()
        g = torch.Generator().manual_seed(0)
        mask = torch.tensor(CHECK_MASK)
        b, agents = mask.shape
        feats = torch.randn(b, agents, channels, CHECK_CELLS, CHECK_CELLS, generator=g)
        expected = (b, channels, CHECK_CELLS, CHECK_CELLS)

        def run(x: Tensor, valid: Tensor, what: str) -> Tensor:
            try:
                with torch.no_grad():
                    out = module(x.clone(), valid.clone())
            except Exception as e:  # noqa: BLE001
                raise fail(f"forward({what}) raised {type(e).__name__}: {_one_line(e)}") from None
            want = (x.shape[0], channels, *x.shape[3:])
            if not isinstance(out, Tensor) or tuple(out.shape) != want or out.dtype != x.dtype:
                dtype = str(x.dtype).removeprefix("torch.")
                raise fail(f"forward({what}) returned {_describe(out)}; expected a {dtype} tensor [B, C, H, W] "
                           f"= {want}")
            if not bool(torch.isfinite(out).all()):
                raise fail(f"forward({what}) returned non-finite values (NaN or inf) from finite features")
            return out

        shape = "x".join(map(str, feats.shape))
        out = run(feats, mask, f"features {shape}, valid_mask {b}x{agents} with absent agents")
        assert tuple(out.shape) == expected
        run(feats[:, :1], mask[:, :1], f"features {b}x1x{channels}x{CHECK_CELLS}x{CHECK_CELLS}: the ego alone")
        absent = ~mask[:, :, None, None, None]
        other = torch.where(absent, torch.randn(feats.shape, generator=g) * 100.0 + 7.0, feats)
        if not torch.equal(run(other, mask, "other features in the absent agents' slots"), out):
            raise fail("the output changes when an absent agent's features change (valid_mask False): absent agents "
                       "must be ignored exactly, bit for bit")
        nonfinite = torch.where(absent, torch.tensor([float("nan"), float("inf"), -float("inf")]).repeat(
            feats.numel() // 3 + 1)[:feats.numel()].view(feats.shape), feats)
        try:
            same = torch.equal(run(nonfinite, mask, "NaN / inf in the absent agents' slots"), out)
        except PluginError as e:
            raise fail("NaN / inf in an absent agent's features reach the output (exclude absent agents with "
                       "torch.where or -inf, never by multiplying with the mask)") from e
        if not same:
            raise fail("the output changes when an absent agent's features are NaN / inf: absent agents must be "
                       "ignored exactly, bit for bit")


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())[:300]
