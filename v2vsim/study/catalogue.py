"""The closed-loop benchmark's catalogue (scenarios/benchmark/catalogue.yaml, docs/benchmark.md): the scenario
families, each a shipped scenario with a grid of its critical actor's factors (as Coopernaut's: the collider's
timing x its speed), the methods ranked, the tuning and held-out seeds, and the profiles that pick a share of all
that. Parsed once into frozen dataclasses; a malformed file is one ConfigError naming the file and the key.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from models.registry import METHODS
from v2vsim.config import ConfigError, parse_override
from v2vsim.config.shipped import scenarios_dir
from v2vsim.study.grid import Axis, parse_axis, parse_seeds

ORACLE = "oracle"
SPLITS = ("tuning", "heldout")


@dataclass(frozen=True)
class Family:
    """One pre-crash scenario family: a scenario file and its grid of configurations."""

    name: str
    scenario: Path
    pre_crash: str  # the NHTSA pre-crash typology's name for the conflict
    occlusion: str  # who cannot see whom, and what hides it
    grid: tuple[Axis, ...]  # the critical actor's factors, timing first
    sees: tuple[str, ...] = ()  # the CAVs that see the hidden actor (`--driven sees` drives them beside the ego)

    def axes(self, levels: Sequence[int]) -> tuple[Axis, ...]:
        """The grid with `levels[i]` evenly spaced values kept on axis i (1: the middle one; absent: 1; at least the
        axis's length: all of them)."""
        return tuple(_thin(a, levels[i] if i < len(levels) else 1) for i, a in enumerate(self.grid))


@dataclass(frozen=True)
class Profile:
    """How much of the catalogue a benchmark runs."""

    name: str
    seeds: int  # the first this many of the split's seeds
    levels: tuple[int, ...]  # values kept per grid axis (Family.axes)
    methods: tuple[str, ...]


@dataclass(frozen=True)
class Stress:
    """One degradation axis of the stress study (v2vsim.study.stress): a scenario key and its levels, mildest
    first."""

    name: str
    level: Axis  # the key and its levels (a level may be a mapping: comm.pose_noise={xy_std_m: .., ..})
    x: tuple[float, ...]  # each level's position on the plots and in the tables
    unit: str  # what x measures
    compensation: bool  # also run the methods that have compensation with it on
    sets: tuple[str, ...] = ()  # overrides of every stressed run (KEY.PATH=VALUE)


@dataclass(frozen=True)
class Catalogue:
    source: Path
    methods: tuple[str, ...]  # every method the full benchmark ranks, oracle and none first
    seeds: dict[str, tuple[int, ...]]  # split -> seeds (tuning: calibration only; heldout: the leaderboard)
    profiles: dict[str, Profile]
    families: tuple[Family, ...]
    stresses: dict[str, Stress] = field(default_factory=dict)  # name -> degradation axis (`--stress`)

    def stress(self, name: str) -> Stress:
        if name not in self.stresses:
            raise ConfigError(f"{self.source}: no stress {name!r}; stresses: {', '.join(self.stresses) or 'none'}")
        return self.stresses[name]

    def family(self, name: str) -> Family:
        for f in self.families:
            if f.name == name:
                return f
        raise ConfigError(f"{self.source}: no family {name!r}; families: {', '.join(f.name for f in self.families)}")


def default_catalogue() -> Path:
    folder = scenarios_dir()
    if folder is None or not (folder / "benchmark" / "catalogue.yaml").is_file():
        raise ConfigError("no benchmark catalogue in this install (scenarios/benchmark/catalogue.yaml); pass "
                          "--catalogue FILE")
    return folder / "benchmark" / "catalogue.yaml"


def _thin(a: Axis, n: int) -> Axis:
    m = len(a.texts)
    if n >= m:
        return a
    idx = [m // 2] if n == 1 else sorted({round(i * (m - 1) / (n - 1)) for i in range(n)})
    return Axis(a.key, tuple(a.texts[i] for i in idx), tuple(a.values[i] for i in idx))


class _Reader:
    """Field access that names the file and the key path of what is wrong."""

    def __init__(self, source: Path) -> None:
        self.source = source

    def fail(self, where: str, why: str) -> ConfigError:
        return ConfigError(f"{self.source}: {where}: {why}")

    def mapping(self, v: Any, where: str, keys: set[str], required: set[str]) -> dict:
        if not isinstance(v, dict):
            raise self.fail(where, f"expected a mapping, got {type(v).__name__}")
        unknown = sorted(set(v) - keys)
        if unknown:
            raise self.fail(f"{where}.{unknown[0]}" if where else unknown[0],
                            f"unknown key; allowed: {', '.join(sorted(keys))}")
        missing = sorted(required - set(v))
        if missing:
            raise self.fail(f"{where}.{missing[0]}" if where else missing[0], "missing")
        return v

    def text(self, v: Any, where: str) -> str:
        if not isinstance(v, str) or not v.strip():
            raise self.fail(where, f"expected a non-empty string, got {v!r}")
        return v.strip()

    def count(self, v: Any, where: str) -> int:
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise self.fail(where, f"expected an integer >= 1, got {v!r}")
        return v

    def axis(self, key: str, values: list[Any], where: str) -> Axis:
        """A swept key from YAML values, each parsed as `--grid KEY=...` parses it (so a mapping level is a value)."""
        texts = ",".join(yaml.safe_dump(v, default_flow_style=True).strip().removesuffix("\n...").strip()
                         for v in values)
        try:
            return parse_axis(f"{key}={texts}")
        except ConfigError as e:
            raise self.fail(where, str(e)) from None

    def methods(self, v: Any, where: str) -> tuple[str, ...]:
        allowed = (ORACLE, *METHODS)
        if not isinstance(v, list) or not v:
            raise self.fail(where, f"expected a non-empty list of {', '.join(allowed)}")
        for i, m in enumerate(v):
            if m not in allowed:
                raise self.fail(f"{where}[{i}]", f"{m!r} is no method; allowed: {', '.join(allowed)}")
        if len(set(v)) != len(v):
            raise self.fail(where, "a method is listed twice")
        return tuple(v)


def load_catalogue(path: Path | None = None) -> Catalogue:
    """Read and check a catalogue (default: the shipped one). Each family's scenario must load with every value of
    its grid (checked by the benchmark before anything runs, with the profile's overrides)."""
    source = (path or default_catalogue()).resolve()
    r = _Reader(source)
    try:
        raw = yaml.safe_load(source.read_text(encoding="utf-8"))
    except OSError as e:
        raise ConfigError(f"{source}: cannot read the catalogue: {e.strerror or e}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{source}: not valid YAML: {' '.join(str(e).split())}") from None
    top = r.mapping(raw, "", {"methods", "seeds", "profiles", "families", "stress"},
                    {"methods", "seeds", "profiles", "families"})
    methods = r.methods(top["methods"], "methods")
    if methods[:2] != (ORACLE, "none"):
        raise r.fail("methods", "must start with oracle, none (the references every method is scored against)")
    seeds_raw = r.mapping(top["seeds"], "seeds", set(SPLITS), set(SPLITS))
    seeds: dict[str, tuple[int, ...]] = {}
    for split in SPLITS:
        try:
            seeds[split] = tuple(parse_seeds(str(seeds_raw[split])))
        except ConfigError as e:
            raise r.fail(f"seeds.{split}", str(e)) from None
    if set(seeds["tuning"]) & set(seeds["heldout"]):
        raise r.fail("seeds", "tuning and heldout seeds overlap; the leaderboard's seeds are never calibrated on")
    profiles: dict[str, Profile] = {}
    for name, p in r.mapping(top["profiles"], "profiles", set(top["profiles"] or {}), set()).items():
        where = f"profiles.{name}"
        p = r.mapping(p, where, {"seeds", "levels", "methods"}, {"seeds", "levels"})
        levels = p["levels"]
        if not isinstance(levels, list) or not levels:
            raise r.fail(f"{where}.levels", "expected a list of integers >= 1 (values kept per grid axis)")
        ps = Profile(name, r.count(p["seeds"], f"{where}.seeds"),
                     tuple(r.count(v, f"{where}.levels[{i}]") for i, v in enumerate(levels)),
                     r.methods(p["methods"], f"{where}.methods") if "methods" in p else methods)
        stray = [m for m in ps.methods if m not in methods]
        if stray:
            raise r.fail(f"{where}.methods", f"{stray[0]!r} is not among the catalogue's methods")
        profiles[name] = ps
    if not profiles:
        raise r.fail("profiles", "expected at least one profile")
    if not isinstance(top["families"], list) or not top["families"]:
        raise r.fail("families", "expected a non-empty list of families")
    families = []
    for i, f in enumerate(top["families"]):
        where = f"families[{i}]"
        f = r.mapping(f, where, {"name", "scenario", "pre_crash", "occlusion", "grid", "sees"},
                      {"name", "scenario", "grid"})
        sees = f.get("sees", [])
        if not isinstance(sees, list) or not all(isinstance(c, str) and c for c in sees):
            raise r.fail(f"{where}.sees", "expected a list of CAV ids (those that see the hidden actor)")
        name = r.text(f["name"], f"{where}.name")
        scenario = (source.parent / r.text(f["scenario"], f"{where}.scenario")).resolve()
        if not scenario.is_file():
            raise r.fail(f"{where}.scenario", f"no such file: {scenario}")
        grid = f["grid"]
        if not isinstance(grid, dict) or not grid:
            raise r.fail(f"{where}.grid", "expected a mapping KEY.PATH: [values, ...]")
        axes = []
        for key, values in grid.items():
            if not isinstance(values, list) or not values:
                raise r.fail(f"{where}.grid.{key}", "expected a non-empty list of values")
            axes.append(r.axis(key, values, f"{where}.grid.{key}"))
        families.append(Family(name, scenario, str(f.get("pre_crash", "")), str(f.get("occlusion", "")),
                               tuple(axes), tuple(sees)))
    names = [f.name for f in families]
    if len(set(names)) != len(names):
        raise r.fail("families", "two families share a name")
    return Catalogue(source, methods, seeds, profiles, tuple(families), _stresses(r, top.get("stress") or {}))


def _stresses(r: _Reader, raw: Any) -> dict[str, Stress]:
    """The `stress` section: name -> {key, levels, x (default: the levels, when numbers), unit, compensation,
    set (overrides of every stressed run), harsher (up | down: which way along x the levels grow harsher)}."""
    out: dict[str, Stress] = {}
    for name, st in r.mapping(raw, "stress", set(raw or {}), set()).items():
        where = f"stress.{name}"
        st = r.mapping(st, where, {"key", "levels", "x", "unit", "compensation", "set", "harsher"},
                        {"key", "levels", "unit"})
        levels = st["levels"]
        if not isinstance(levels, list) or len(levels) < 2:
            raise r.fail(f"{where}.levels", "expected a list of at least two levels, mildest first")
        key = r.text(st["key"], f"{where}.key")
        axis = r.axis(key, levels, f"{where}.levels")
        x = st.get("x", levels)
        if (not isinstance(x, list) or len(x) != len(levels)
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in x)):
            raise r.fail(f"{where}.x", f"expected {len(levels)} numbers (each level's position; needed when the "
                                       "levels are not numbers)")
        # harsher: which way along x the levels grow harsher (up: latency, loss; down: penetration, where fewer
        # connected vehicles is the harsher level); the levels are listed mildest first either way
        harsher = st.get("harsher", "up")
        if harsher not in ("up", "down"):
            raise r.fail(f"{where}.harsher", f"expected 'up' or 'down', got {harsher!r}")
        sign = 1 if harsher == "up" else -1
        if any(sign * (b - a) <= 0 for a, b in zip(x, x[1:], strict=False)):
            raise r.fail(f"{where}.x", f"expected {'in' if sign > 0 else 'de'}creasing numbers, mildest level first"
                                       f" (harsher: {harsher})")
        comp = st.get("compensation", False)
        if not isinstance(comp, bool):
            raise r.fail(f"{where}.compensation", f"expected true or false, got {comp!r}")
        sets = st.get("set", [])
        if not isinstance(sets, list) or not all(isinstance(o, str) and "=" in o for o in sets):
            raise r.fail(f"{where}.set", "expected a list of KEY.PATH=VALUE overrides")
        for i, o in enumerate(sets):
            try:
                parse_override(o)
            except ConfigError as e:
                raise r.fail(f"{where}.set[{i}]", str(e)) from None
        out[name] = Stress(name, axis, tuple(float(v) for v in x), r.text(st["unit"], f"{where}.unit"), comp,
                           tuple(sets))
    return out
