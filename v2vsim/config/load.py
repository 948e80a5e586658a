"""Reading a scenario: the strict YAML loader, --set overrides, `load_scenario` and `scenario_from_dict`."""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path
from typing import Any

import yaml

from v2vsim.config.checks import _check_cross_fields
from v2vsim.config.errors import ConfigError
from v2vsim.config.schema import Scenario
from v2vsim.config.shipped import find_scenario
from v2vsim.config.validate import _Loader


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key given twice in one mapping (PyYAML silently keeps the last,
    so a scenario would run with a value its author did not mean)."""


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen: dict[Any, int] = {}  # explicit keys only: one may override a key merged in with `<<`
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node, deep=deep)
        try:
            line = seen.get(key)
        except TypeError:  # an unhashable key: construct_mapping reports it
            break
        if line is not None:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r} (first at line {line + 1})", key_node.start_mark)
        seen[key] = key_node.start_mark.line
    return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def _yaml_load(text: str) -> Any:
    return yaml.load(text, Loader=_StrictLoader)  # a SafeLoader subclass: no arbitrary objects


def _yaml_problem(e: yaml.YAMLError) -> str:
    """What PyYAML says is wrong, on one line (a ReaderError has no `problem`, and str() spans lines)."""
    problem = getattr(e, "problem", None) or getattr(e, "reason", None) or str(e)
    return " ".join(str(problem).split())


def parse_override(text: str) -> tuple[list[str], Any]:
    """'comm.drop.p=0.3' -> (['comm', 'drop', 'p'], 0.3); the value is parsed as a YAML scalar."""
    if "=" not in text:
        raise ConfigError(f"--set {text}: expected key.path=value")
    key, _, val = text.partition("=")
    key = key.strip()
    if not key or any(not part for part in key.split(".")):
        raise ConfigError(f"--set {text}: bad key path {key!r}")
    try:
        value = _yaml_load(val) if val.strip() else None
    except yaml.YAMLError as e:
        raise ConfigError(f"--set {text}: value is not valid YAML ({_yaml_problem(e)})") from None
    return key.split("."), value


def apply_overrides(raw: dict, overrides: typing.Sequence[str]) -> dict:
    """Write each --set into the raw mapping (before validation, so it gets the same checks)."""
    for text in overrides:
        keys, value = parse_override(text)
        node = raw
        for k in keys[:-1]:
            child = node.get(k)
            if child is None:
                child = node[k] = {}
            if not isinstance(child, dict):
                raise ConfigError(f"--set {text}: {k} is not a mapping")
            node = child
        node[keys[-1]] = value
    return raw


def load_scenario(path: str | Path, overrides: typing.Sequence[str] = ()) -> Scenario:
    """Read, override and validate a scenario YAML, given by path or by a shipped scenario's name (`source` is
    then the file in the package: child processes get that path). Raises ConfigError with a clear message."""
    path = find_scenario(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not a text (UTF-8) file: byte {e.start} is 0x{e.object[e.start]:02x}; "
                          "a scenario is a YAML file") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot read the scenario file: {e.strerror or e}") from None
    try:
        raw = _yaml_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(f"{path}: not valid YAML{where}: {_yaml_problem(e)}") from None
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of keys, got {type(raw).__name__}")
    raw = apply_overrides(raw, overrides)
    loader = _Loader(str(path), path.parent)
    sc = loader.section(Scenario, raw, "")
    sc = dataclasses.replace(sc, source=str(path), overrides=tuple(overrides))
    _check_cross_fields(sc, loader)
    return resolve_perceive(resolve_auth(sc))


def scenario_from_dict(raw: dict, base_dir: Path | None = None, source: str = "<dict>") -> Scenario:
    """Validate an in-memory mapping (tests, PettingZoo env)."""
    loader = _Loader(source, base_dir)
    sc = dataclasses.replace(loader.section(Scenario, raw, ""), source=source)
    _check_cross_fields(sc, loader)
    return resolve_perceive(resolve_auth(sc))


def resolve_perceive(sc: Scenario) -> Scenario:
    """control.perceive driving: perception.methods becomes the one method the ego drives on (oracle: none), so
    every process (the CAVs ship only what it reads, the ego fuses only it) and metrics.json hold what ran."""
    c = sc.control
    if c is None or c.perceive != "driving":
        return sc
    methods = ("none",) if c.method == "oracle" else (c.method,)
    return dataclasses.replace(sc, perception=dataclasses.replace(sc.perception, methods=methods))


def neighbours_silent(sc: Scenario) -> bool:
    """Whether the other CAVs need not encode nor send a map: a closed-loop point that computes only `none` (control
    perceive driving, method none or oracle), which reads the ego's own map alone. They still sense (what they see
    is the ground truth's visible set) and their vehicles drive on; an open-loop run is left as it was."""
    return sc.control is not None and sc.control.perceive == "driving" and set(sc.perception.methods) <= {"none"}


def resolve_auth(sc: Scenario) -> Scenario:
    """comm.auth.identity auto -> per_process, or off when comm.auth.key_file gives a shared key instead: every
    process that loads the scenario resolves it alike, and metrics.json and recordings hold what ran."""
    auth = sc.comm.auth
    if auth.identity != "auto":
        return sc
    identity = "off" if auth.key_file is not None else "per_process"
    return dataclasses.replace(sc, comm=dataclasses.replace(sc.comm, auth=dataclasses.replace(auth, identity=identity)))
