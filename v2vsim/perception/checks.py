"""Model-dependent checks of a scenario, run before any process starts (the runner, `v2vsim evaluate`): what the
schema cannot check because it needs torch, the zoo's files or the host's devices."""

from __future__ import annotations

from models.presets import get_preset
from v2vsim.config import ConfigError, Scenario, check_plugins
from v2vsim.perception.aligned import build_aligned_encoder
from v2vsim.perception.build import (
    build_agent_encoder,
    build_compressor,
    build_method_models,
    runnable_methods,
    wire_ratio,
    zoo_for,
)
from v2vsim.perception.device import resolve_device
from v2vsim.perception.fleet import extra_types


def check_scenario(sc: Scenario) -> None:
    """Model-dependent checks the schema cannot make; ConfigError before any process starts."""
    try:  # the loader imports no torch: whether this host has the device asked for is known only here
        resolve_device(sc.perception.device)
    except ConfigError as e:
        raise ConfigError(f"{sc.source}: {e}") from None
    check_plugins(sc)
    channels = get_preset(sc.perception.preset).channels
    ratio = wire_ratio(sc)
    if channels % ratio:
        raise ConfigError(f"{sc.source}: comm.channel_compression: {ratio} does not divide the {channels} feature "
                          f"channels of preset {sc.perception.preset!r}; allowed: a divisor of {channels}")
    build_compressor(sc, channels)
    if not runnable_methods(sc):
        raise ConfigError(f"{sc.source}: perception.methods: nothing to run for modality "
                          f"{sc.perception.modality!r} (early fusion needs LiDAR)")
    for t in extra_types(sc):  # a mixed fleet: each type's aligned encoder, verified against this base
        build_aligned_encoder(sc, t.encoder)
    # every checkpoint a process loads is verified (sha256, and that it fits its model) before any starts;
    # building the models reads each file once (~0.3 s for the tiny zoo)
    if zoo_for(sc) is not None:
        build_method_models(sc, build_agent_encoder(sc), runnable_methods(sc))
