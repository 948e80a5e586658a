"""The scenario YAML (DESIGN.md "Scenario YAML"): typed schema, defaults, overrides, clear errors.

A scenario is loaded once into frozen dataclasses (`Scenario`). Each field carries what is
allowed; unknown keys, wrong types and out-of-range values raise `ConfigError` naming the
file, the key path and what is allowed. Input paths are relative to the YAML file;
`output.dir` is relative to the working directory (so a shipped scenario found by name, whose YAML may sit
in a read-only site-packages, writes its runs under the working directory, e.g. runs/intersection).

Modules (each imports only those above it):
- `errors`: `ConfigError`;
- `schema_fields`: `_f`, the field helper whose metadata says what is allowed, and the range checks it shares;
- the sections, frozen dataclasses by topic: `schema_traffic` (traffic, cavs), `schema_perception` (sensors, bev,
  perception, evaluation; `ENCODERS_BY_MODALITY`, `DEVICE_PATTERN`), `schema_comm` (comm, transport),
  `schema_control` (control), `schema_misbehaviour` (misbehaviour, defence);
- `schema`: `Scenario`, the whole YAML, with its top-level fields (`SEED_MAX`) and the `output` section;
- `validate`: `_Loader`, which checks a raw mapping against the schema (types, ranges, unknown keys, paths);
- `checks`: the checks across fields of a loaded scenario, `check_output_dir`, and `check_plugins` (the fusion
  plugins a scenario requests, imported and checked: models.registry);
- `shipped`: the shipped scenarios (names, descriptions, where they are) and `find_scenario`, which turns a
  SCENARIO argument (a path or a shipped name) into a YAML file;
- `load`: the strict YAML loader, `parse_override`, `apply_overrides`, `load_scenario`, `scenario_from_dict`.

The public API is re-exported here: import it from `v2vsim.config` (`METHODS` too: the live list of
models.registry's methods, plugins included, which perception.methods is checked against).
"""

from models.registry import METHODS
from v2vsim.config.checks import check_output_dir, check_plugins
from v2vsim.config.errors import ConfigError
from v2vsim.config.load import apply_overrides, load_scenario, neighbours_silent, parse_override, scenario_from_dict
from v2vsim.config.schema import SEED_MAX, OutputConfig, Scenario
from v2vsim.config.schema_comm import (
    AuthConfig,
    ChannelConfig,
    CommConfig,
    DropConfig,
    LatencyConfig,
    PoseNoiseConfig,
    ShareConfig,
    TransportConfig,
)
from v2vsim.config.schema_control import ControlConfig, IdmConfig, SsmConfig
from v2vsim.config.schema_perception import (
    ENCODERS_BY_MODALITY,
    BevConfig,
    CamerasConfig,
    EvaluationConfig,
    LidarConfig,
    PerceptionConfig,
    SensorsConfig,
)
from v2vsim.config.schema_traffic import CavsConfig, HiddenFoeConfig, MeetConfig, TrafficConfig
from v2vsim.config.shipped import describe, find_scenario, scenarios_dir, shipped_scenarios

__all__ = [
    "ENCODERS_BY_MODALITY",
    "METHODS",
    "SEED_MAX",
    "AuthConfig",
    "BevConfig",
    "CamerasConfig",
    "CavsConfig",
    "ChannelConfig",
    "CommConfig",
    "ConfigError",
    "ControlConfig",
    "DropConfig",
    "EvaluationConfig",
    "HiddenFoeConfig",
    "IdmConfig",
    "LatencyConfig",
    "LidarConfig",
    "MeetConfig",
    "OutputConfig",
    "PerceptionConfig",
    "PoseNoiseConfig",
    "Scenario",
    "SensorsConfig",
    "ShareConfig",
    "SsmConfig",
    "TrafficConfig",
    "TransportConfig",
    "apply_overrides",
    "check_output_dir",
    "check_plugins",
    "describe",
    "find_scenario",
    "load_scenario",
    "neighbours_silent",
    "parse_override",
    "scenario_from_dict",
    "scenarios_dir",
    "shipped_scenarios",
]
