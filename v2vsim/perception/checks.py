"""Model-dependent checks of a scenario, run before any process starts (the runner, `v2vsim evaluate`): what the
schema cannot check because it needs torch, the zoo's files or the host's devices.

Every checkpoint a process of the run loads is verified here (sha256, each distinct file read once) and checked to
fit its model: the models are built with their parameters left uninitialised (_shapes_only) and the keys and shapes of
each checkpoint part compared with theirs, so that a misfit is refused with the message loading it
would give (v2vsim.perception.build._load, load_part), without building every model for real.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch
from torch import nn
from torch.overrides import TorchFunctionMode

from models.build import build_encoder
from models.compression import ChannelCompressor
from models.presets import get_preset
from models.zoo import Checkpoint
from v2vsim.config import ConfigError, Scenario, check_plugins
from v2vsim.perception.aligned import aligned_module, aligned_state
from v2vsim.perception.build import (
    extrapolation_module,
    extrapolation_state,
    method_misfit,
    method_model,
    misfit,
    verified,
)
from v2vsim.perception.device import resolve_device
from v2vsim.perception.plan import ModelPlan, plan_models


def check_scenario(sc: Scenario) -> ModelPlan:
    """Model-dependent checks the schema cannot make (check_plan); ConfigError before any process starts. Returns
    the plan it checked, for the caller's own use of the models' metadata (the runner's notes)."""
    try:  # the loader imports no torch: whether this host has the device asked for is known only here
        resolve_device(sc.perception.device)
    except ConfigError as e:
        raise ConfigError(f"{sc.source}: {e}") from None
    check_plugins(sc)
    plan = plan_models(sc)
    check_plan(plan)
    return plan


def check_plan(plan: ModelPlan) -> None:
    """The plan's wire, methods and every checkpoint its processes load; ConfigError naming what is wrong."""
    channels = get_preset(plan.preset).channels
    ratio = plan.wire_ratio
    if channels % ratio:
        raise ConfigError(f"{plan.source}: comm.channel_compression: {ratio} does not divide the {channels} feature "
                          f"channels of preset {plan.preset!r}; allowed: a divisor of {channels}")
    states = _States()
    if ratio > 1 and plan.zoo is not None:  # random weights: a seeded random compressor, nothing to verify
        ckpt = plan.wire_compressor()
        assert ckpt is not None
        comp = _shapes_only(lambda: ChannelCompressor(channels, ratio))
        _fits(comp, states.of(ckpt), "compressor.", lambda reason: misfit(
            ckpt.path, f"the ratio-{ratio} compressor does not fit", reason,
            f"rebuild it with: {ckpt.rebuild_command}"))
    if not plan.methods:
        raise ConfigError(f"{plan.source}: perception.methods: nothing to run for modality "
                          f"{plan.modality!r} (early fusion needs LiDAR)")
    for encoder in plan.aligned:  # a mixed fleet: each type's aligned encoder, verified against this base
        aligned, state, train = aligned_state(plan, encoder)
        states.seen[aligned.checkpoint.path] = state
        module = _shapes_only(lambda encoder=encoder, aligned=aligned: aligned_module(plan, encoder, aligned))
        _fits(module, state, "encoder.", lambda reason, encoder=encoder, aligned=aligned, train=train: misfit(
            aligned.checkpoint.path, f"the aligned {encoder} encoder does not fit", reason, f"re-align with: {train}"))
    if plan.zoo is None:
        return
    _check_methods(plan, states)


def _check_methods(plan: ModelPlan, states: _States) -> None:
    """The CAVs' encoder, every runnable method and (comm.compensation) each method's extrapolation, as the
    processes load them (v2vsim.perception.build): each part present in its checkpoint fits its module."""
    ckpt = plan.checkpoint("encoder")
    if ckpt is not None:
        encoder = _shapes_only(lambda: build_encoder(plan.encoder, plan.preset, bev_size_m=plan.bev_size_m,
                                                     cells=plan.cells, image_backbone=plan.image_backbone))
        _fits(encoder, states.of(ckpt), "encoder.", lambda reason: method_misfit(ckpt, "encoder.", "encoder", reason),
              optional=True)
    files = {m: plan.checkpoint(m) for m in plan.methods}
    for c in files.values():  # every file verified before any is compared, as build_method_models loads them
        if c is not None:
            states.of(c)
    for m, c in files.items():
        if c is None:
            continue
        model = _shapes_only(lambda m=m: method_model(plan, m))
        parts = (("encoder.", model.encoder),) if m == "early" else ()  # early fusion's encoder: its own weights
        for prefix, module in (*parts, ("fusion.", model.fusion), ("heads.", model.heads)):
            _fits(module, states.of(c), prefix, lambda reason, c=c, prefix=prefix, m=m: method_misfit(
                c, prefix, m, reason), optional=True)
    if not plan.compensation:
        return
    for m in plan.methods:  # the ego loads each one there is (agents.ego_setup.load_models)
        found = extrapolation_state(plan, m)
        if found is not None:
            ext, sub = found
            module = _shapes_only(lambda m=m, ext=ext, sub=sub: extrapolation_module(plan, ext, sub, m, load=False))
            _fits(module, sub, "",
                  lambda reason, m=m, ext=ext: misfit(ext.path, f"the {m} extrapolation weights do not fit", reason,
                                                      f"rebuild it with: {ext.rebuild_command}"))


class _States:
    """Verified state_dicts by file: each checkpoint read and hashed once."""

    def __init__(self) -> None:
        self.seen: dict = {}

    def of(self, ckpt: Checkpoint) -> dict:
        if ckpt.path not in self.seen:
            self.seen[ckpt.path] = verified(ckpt)
        return self.seen[ckpt.path]


def _shapes_only(build: Callable[[], nn.Module]) -> nn.Module:
    """The module `build` makes, its parameters allocated and never initialised: only the keys and shapes of its
    state_dict are read. On the CPU, not the meta device: torch computes on meta tensors (a fill, an anchor grid)
    through torch._refs, whose first call imports torch._dynamo, 2.5 s of every run's start here; the tiny models'
    allocation is cheap, and their random initialisation, the costly part, is skipped."""
    with _NoParameterInit():
        return build()


# torch.nn.init's random initialisers and the Tensor methods they use
_RANDOM_INITS = frozenset({"normal_", "uniform_", "trunc_normal_", "kaiming_normal_", "kaiming_uniform_",
                           "xavier_normal_", "xavier_uniform_", "orthogonal_"})


class _NoParameterInit(TorchFunctionMode):
    """A parameter's random initialiser returns the parameter as it is (whatever the allocator left in it). A
    buffer's runs: a construction may compute on it."""

    def __torch_function__(self, func: Callable[..., Any], types: Any, args: tuple[Any, ...] = (),
                           kwargs: dict[str, Any] | None = None) -> Any:
        kwargs = kwargs or {}
        if getattr(func, "__name__", "") in _RANDOM_INITS:
            target = args[0] if args else kwargs.get("tensor")  # torch.nn.init passes it by name
            if isinstance(target, nn.Parameter):
                return target
        return func(*args, **kwargs)


def _fits(module: nn.Module, state: Mapping[str, torch.Tensor], prefix: str,
          error: Callable[[str], ConfigError], optional: bool = False) -> None:
    """The `prefix` part of a verified checkpoint's `state` fits `module` (the keys and shapes load_state_dict
    requires); `error(reason)`, the reason worded as load_state_dict words it, where it does not. `optional`: a
    checkpoint without that part is fine (the module keeps its seeded weights, as _load does)."""
    sub = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
    if optional and not sub:
        return
    reason = _mismatch(module, sub)
    if reason is not None:
        raise error(reason)


def _mismatch(module: nn.Module, sub: Mapping[str, torch.Tensor]) -> str | None:
    """What module.load_state_dict(sub) (strict) would refuse, in its words; None when it would load."""
    want = module.state_dict()
    missing = [k for k in want if k not in sub]
    unexpected = [k for k in sub if k not in want]
    msgs = []
    if missing:
        msgs.append(f"Missing key(s) in state_dict: {_quoted(missing)}. ")
    if unexpected:
        msgs.append(f"Unexpected key(s) in state_dict: {_quoted(unexpected)}. ")
    for k, v in want.items():
        got = sub.get(k)
        if got is None or (v.dim() == 0 and got.dim() == 1):  # a 0-d parameter loads from a 1-element vector
            continue
        if got.shape != v.shape:
            msgs.append(f"size mismatch for {k}: copying a param with shape {got.shape} from checkpoint, the shape "
                        f"in current model is {v.shape}.")
    if not msgs:
        return None
    return f"Error(s) in loading state_dict for {module.__class__.__name__}:\n\t" + "\n\t".join(msgs)


def _quoted(keys: list[str]) -> str:
    return ", ".join('"' + k + '"' for k in keys)
