"""The scenario YAML (DESIGN.md "Scenario YAML"): typed schema, defaults, overrides, clear errors.

A scenario is loaded once into frozen dataclasses (`Scenario`). Each field carries what is
allowed; unknown keys, wrong types and out-of-range values raise `ConfigError` naming the
file, the key path and what is allowed. Input paths are relative to the YAML file;
`output.dir` is relative to the working directory.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import tempfile
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

SEED_MAX = 2**31 - 1  # SUMO (libsumo --seed) takes a signed 32-bit seed
METHODS = ("none", "late", "early", "attfuse", "fcooper", "v2vnet", "disconet", "cobevt")
ENCODERS_BY_MODALITY = {"lidar": ("pointpillars",), "camera": ("sinbevt", "lara")}


class ConfigError(Exception):
    """A scenario problem a user can fix: the message names the file, key path and what is allowed."""


# ---- field helpers: metadata says what is allowed -------------------------------------------


def _f(default: Any, allowed: str = "", check: typing.Callable[[Any], bool] | None = None,
       path: str | None = None) -> Any:
    """A dataclass field with a range check. `path`: "file" (must exist) or "file?" (optional)."""
    meta = {"allowed": allowed, "check": check, "path": path}
    if isinstance(default, (list, dict)) or dataclasses.is_dataclass(default):
        return field(default_factory=lambda: default, metadata=meta)
    return field(default=default, metadata=meta)


def _pos(x: float) -> bool:
    return x > 0


def _nonneg(x: float) -> bool:
    return x >= 0


def _prob(x: float) -> bool:
    return 0.0 <= x <= 1.0


# ---- the schema ------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrafficConfig:
    backend: Literal["sumo", "highway-env"] = "sumo"
    net: str | None = _f(None, "path to a SUMO .net.xml, relative to the YAML", path="file?")
    buildings: str | None = _f(None, "path to a SUMO .poly.xml, relative to the YAML", path="file?")
    background_per_hour: float = _f(900.0, ">= 0", _nonneg)
    warmup_s: float = _f(10.0, ">= 0 (background traffic runs this long before frame 0)", _nonneg)
    building_height_m: tuple[float, float] = _f((8.0, 15.0), "[lo, hi] with 0 < lo <= hi",
                                                lambda v: 0 < v[0] <= v[1])


@dataclass(frozen=True)
class MeetConfig:
    """What CAV placement aims for (see v2vsim/traffic/sumo.py): at least `neighbours` other CAVs
    within comm.range_m of the first ego in at least `share` of the frames, counted from frame 0."""

    neighbours: int = _f(2, ">= 0 (capped at cavs.count - 1)", _nonneg)
    share: float = _f(0.9, "0..1", _prob)
    trials: int = _f(24, "1..200 (candidate placements simulated ahead; 1 = the first candidate only)",
                     lambda v: 1 <= v <= 200)


@dataclass(frozen=True)
class CavsConfig:
    count: int = _f(4, "1..16", lambda v: 1 <= v <= 16)
    ego: str | tuple[str, ...] = _f("first", "'first', 'all' or a list of CAV ids",
                                    lambda v: not isinstance(v, str) or v in ("first", "all"))
    arrival_s: tuple[float, float] = _f((0.0, 4.0), "[lo, hi] with 0 <= lo <= hi <= 60 (seconds after frame 0 "
                                        "at which the CAVs reach the junction at free-flow speed)",
                                        lambda v: 0 <= v[0] <= v[1] <= 60)
    meet: MeetConfig = field(default_factory=MeetConfig)


@dataclass(frozen=True)
class LidarConfig:
    channels: int = _f(32, ">= 1", _pos)
    points_per_channel: int = _f(1024, ">= 1", _pos)
    range_m: float = _f(100.0, "> 0", _pos)
    vertical_fov_deg: tuple[float, float] = _f((-25.0, 5.0), "[lo, hi] with -90 <= lo < hi <= 90",
                                               lambda v: -90 <= v[0] < v[1] <= 90)
    height_m: float = _f(1.9, "> 0", _pos)
    noise_std_m: float = _f(0.02, ">= 0", _nonneg)
    dropout: float = _f(0.0, "0..1", _prob)


@dataclass(frozen=True)
class CamerasConfig:
    count: int = _f(4, "4 (front, right, left, back)", lambda v: v == 4)
    fov_deg: float = _f(110.0, "0 < fov < 180", lambda v: 0 < v < 180)
    width: int = _f(800, ">= 16", lambda v: v >= 16)
    height: int = _f(600, ">= 16", lambda v: v >= 16)
    render_scale: float = _f(0.25, "0 < scale <= 1", lambda v: 0 < v <= 1)
    height_m: float = _f(1.6, "> 0 (mount height)", _pos)


@dataclass(frozen=True)
class SensorsConfig:
    lidar: LidarConfig = field(default_factory=LidarConfig)
    cameras: CamerasConfig = field(default_factory=CamerasConfig)


@dataclass(frozen=True)
class BevConfig:
    size_m: float = _f(100.0, "> 0", _pos)
    cells: int = _f(256, ">= 8", lambda v: v >= 8)


@dataclass(frozen=True)
class LatencyConfig:
    mean: float = _f(0.0, ">= 0 (ms)", _nonneg)
    jitter: float = _f(0.0, ">= 0 (ms, std of the distribution)", _nonneg)
    distribution: Literal["normal", "uniform", "exponential"] = "normal"


@dataclass(frozen=True)
class DropConfig:
    model: Literal["bernoulli", "gilbert_elliott"] = "bernoulli"
    p: float = _f(0.0, "0..1", _prob)
    p_gb: float = _f(0.0, "0..1 (good -> bad transition probability)", _prob)
    p_bg: float = _f(1.0, "0..1 (bad -> good transition probability)", _prob)
    loss_good: float = _f(0.0, "0..1", _prob)
    loss_bad: float = _f(1.0, "0..1", _prob)


@dataclass(frozen=True)
class PoseNoiseConfig:
    xy_std_m: float = _f(0.0, ">= 0", _nonneg)
    yaw_std_deg: float = _f(0.0, ">= 0", _nonneg)


@dataclass(frozen=True)
class AuthConfig:
    key_file: str | None = _f(None, "path to a secret key file, relative to the YAML", path="file?")


@dataclass(frozen=True)
class ChannelConfig:
    """The radio channel (v2vsim/comm/tr37885.py). `disk`: delivered within comm.range_m, lost only by comm.drop.
    `tr37885`: within comm.range_m, reception decided by the link budget over 3GPP TR 37.885 path loss with the
    link state (los | nlos | nlosv) from the world's buildings and vehicles; serialisation at the MCS data rate
    (capped by comm.bandwidth_mbps when that is lower). Defaults: TR 37.885 / IEEE 802.11p values (see tr37885.py)."""

    model: Literal["disk", "tr37885"] = "disk"
    scenario: Literal["urban", "highway"] = "urban"  # TR 37.885 Table 6.2.1-1 LOS formula and decorrelation distance
    carrier_ghz: float = _f(5.9, "0.5..100 (GHz)", lambda v: 0.5 <= v <= 100)
    tx_power_dbm: float = _f(23.0, "-50..60 (dBm)", lambda v: -50 <= v <= 60)
    antenna_gain_dbi: float = _f(3.0, "-30..30 (dBi, each of the two antennas)", lambda v: -30 <= v <= 30)
    noise_figure_db: float = _f(9.0, "0..30 (dB)", lambda v: 0 <= v <= 30)
    bandwidth_mhz: float = _f(10.0, "5, 10 or 20 (MHz, an IEEE 802.11 OFDM channel width)", lambda v: v in (5, 10, 20))
    mcs: int = _f(2, "0..7 (IEEE 802.11p MCS: BPSK 1/2 .. 64-QAM 3/4)", lambda v: 0 <= v <= 7)
    antenna_height_m: float = _f(1.5, "> 0 (m above each vehicle's pose.z)", _pos)
    per_slope_db: float = _f(1.0, ">= 0 (dB; logistic packet-error slope, 0 = a hard SNR threshold)", _nonneg)


@dataclass(frozen=True)
class ShareConfig:
    """What each CAV sends of its BEV features (v2vsim/comm/sparse.py). `all`: the whole map. `topk`: the `fraction`
    of its feature cells that its own single-agent vehicle confidence ranks highest (Where2comm's spatial
    confidence, Eq. 2), as a sparse message of indices + values, or the whole map where that is no larger."""

    policy: Literal["all", "topk"] = "all"
    fraction: float = _f(1.0, "0..1 (share of the BEV feature cells sent)", _prob)


@dataclass(frozen=True)
class CommConfig:
    range_m: float = _f(70.0, "> 0", _pos)
    latency_ms: LatencyConfig = field(default_factory=LatencyConfig)
    drop: DropConfig = field(default_factory=DropConfig)
    bandwidth_mbps: float | None = _f(27.0, "> 0 or null (unlimited)", _pos)
    max_age_ms: float = _f(500.0, "> 0", _pos)
    pose_noise: PoseNoiseConfig = field(default_factory=PoseNoiseConfig)
    compression: Literal["none", "zlib"] = "none"
    channel_compression: int = _f(1, "1 (off) or a reduction ratio such as 8, 16, 32, 64", _pos)
    auth: AuthConfig = field(default_factory=AuthConfig)
    channel: ChannelConfig = field(default_factory=ChannelConfig)
    # per_link: every (sender, receiver) link has its own data rate; shared: one broadcast channel for every
    # CAV, one transmission at a time, with its busy ratio measured (v2vsim/comm/medium.py)
    medium: Literal["per_link", "shared"] = "per_link"
    share: ShareConfig = field(default_factory=ShareConfig)


@dataclass(frozen=True)
class TransportConfig:
    mode: Literal["peer", "client"] = "peer"  # peer: a loopback mesh; client: through transport.connect routers
    connect: tuple[str, ...] = _f((), "zenoh endpoints such as tcp/127.0.0.1:7447")
    listen: tuple[str, ...] = _f((), "zenoh endpoints; empty = a free loopback port")
    clock: Literal["lockstep", "realtime"] = "lockstep"
    # lockstep: frames the driver and CAVs may run ahead of the slowest ego (0 = strict lockstep);
    # results are the same for any value, only the wall time changes.
    pipeline: int = _f(2, "an integer 0..16", lambda v: 0 <= v <= 16)


@dataclass(frozen=True)
class PerceptionConfig:
    modality: Literal["lidar", "camera"] = "lidar"
    encoder: Literal["pointpillars", "sinbevt", "lara"] = "pointpillars"
    preset: Literal["tiny", "paper"] = "tiny"
    methods: tuple[str, ...] = _f(METHODS, f"a non-empty list of {', '.join(METHODS)}",
                                  lambda v: len(v) > 0 and all(m in METHODS for m in v))
    weights: str = _f("auto", "'auto', 'none' or a checkpoint path")


@dataclass(frozen=True)
class EvaluationConfig:
    # How AP ranks detections: 'global' sorts every detection of the run by score (OpenCOOD's
    # --global_sort_detections, the DESIGN.md default); 'per_frame' keeps frame order and sorts
    # only within each frame (OpenCOOD's default, which most published AP tables use).
    ap_sort: Literal["global", "per_frame"] = "global"


@dataclass(frozen=True)
class OutputConfig:
    dir: str = "runs/intersection"
    rerun: bool = True


@dataclass(frozen=True)
class Scenario:
    name: str = "scenario"
    seed: int = _f(0, f"0..{SEED_MAX}", lambda v: 0 <= v <= SEED_MAX)
    duration_s: float = _f(20.0, "> 0", _pos)
    rate_hz: float = _f(10.0, "> 0", _pos)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    cavs: CavsConfig = field(default_factory=CavsConfig)
    sensors: SensorsConfig = field(default_factory=SensorsConfig)
    bev: BevConfig = field(default_factory=BevConfig)
    comm: CommConfig = field(default_factory=CommConfig)
    transport: TransportConfig = field(default_factory=TransportConfig)
    perception: PerceptionConfig = field(default_factory=PerceptionConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    source: str = field(default="<defaults>", metadata={"internal": True})  # the YAML file
    overrides: tuple[str, ...] = field(default=(), metadata={"internal": True})  # --set, for child processes

    @property
    def frames(self) -> int:
        return max(1, round(self.duration_s * self.rate_hz))

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz


# ---- loading ---------------------------------------------------------------------------------


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return " | ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if origin is tuple:
        args = typing.get_args(tp)
        inner = _type_name(args[0]) if args else "value"
        return f"a list of {inner}" + (f" ({len(args)} items)" if args and args[-1] is not Ellipsis else "")
    if dataclasses.is_dataclass(tp):
        return "a mapping"
    return {int: "an integer", float: "a number", str: "a string", bool: "true/false",
            type(None): "null"}.get(tp, str(tp))


class _Loader:
    def __init__(self, source: str, base_dir: Path | None) -> None:
        self.source = source
        self.base_dir = base_dir

    def fail(self, key: str, msg: str) -> typing.NoReturn:
        raise ConfigError(f"{self.source}: {key}: {msg}")

    def value(self, tp: Any, raw: Any, key: str) -> Any:
        origin = typing.get_origin(tp)
        if dataclasses.is_dataclass(tp):
            return self.section(tp, raw, key)
        if origin is Literal:
            if raw not in typing.get_args(tp):
                hint = difflib.get_close_matches(str(raw), [str(a) for a in typing.get_args(tp)], 1)
                extra = f" (did you mean {hint[0]!r}?)" if hint else ""
                self.fail(key, f"got {raw!r}; allowed: {_type_name(tp)}{extra}")
            return raw
        if origin in (typing.Union, types.UnionType):
            args = typing.get_args(tp)
            if raw is None and type(None) in args:
                return None
            errors = []
            for a in args:
                if a is type(None):
                    continue
                try:
                    return self.value(a, raw, key)
                except ConfigError as e:
                    errors.append(e)
            self.fail(key, f"got {raw!r}; expected {_type_name(tp)}")
        if origin is tuple:
            if not isinstance(raw, (list, tuple)):
                self.fail(key, f"got {raw!r}; expected {_type_name(tp)}")
            args = typing.get_args(tp)
            if args and args[-1] is not Ellipsis:
                if len(raw) != len(args):
                    self.fail(key, f"got {len(raw)} items; expected {_type_name(tp)}")
                pairs = enumerate(zip(args, raw, strict=True))
                return tuple(self.value(a, r, f"{key}[{i}]") for i, (a, r) in pairs)
            return tuple(self.value(args[0], r, f"{key}[{i}]") for i, r in enumerate(raw))
        if tp is bool:
            if not isinstance(raw, bool):
                self.fail(key, f"got {raw!r}; expected true/false")
            return raw
        if tp is int:
            if isinstance(raw, bool) or not isinstance(raw, int):
                self.fail(key, f"got {raw!r}; expected an integer")
            return raw
        if tp is float:
            if isinstance(raw, bool) or not isinstance(raw, (int, float)):
                self.fail(key, f"got {raw!r}; expected a number")
            try:
                value = float(raw)
            except OverflowError:  # an integer beyond any float
                value = math.inf
            if not math.isfinite(value):  # .inf/.nan pass every range check and break frame counts later
                self.fail(key, f"got {raw!r}; expected a finite number")
            return value
        if tp is str:
            if not isinstance(raw, (str, int, float)) or isinstance(raw, bool):
                self.fail(key, f"got {raw!r}; expected a string")
            return str(raw)
        raise TypeError(f"schema type {tp} not handled")  # a bug in the schema, not user input

    def section(self, cls: type, raw: Any, key: str) -> Any:
        if raw is None:
            raw = {}
        if not isinstance(raw, dict):
            self.fail(key or "<top level>", f"got {raw!r}; expected a mapping")
        hints = typing.get_type_hints(cls)
        fields = {f.name: f for f in dataclasses.fields(cls) if not f.metadata.get("internal")}
        for k in raw:
            if k not in fields:
                where = f"{key}.{k}" if key else str(k)
                hint = difflib.get_close_matches(str(k), list(fields), 1)
                extra = f" (did you mean {hint[0]!r}?)" if hint else ""
                self.fail(where, f"unknown key{extra}; allowed here: {', '.join(fields)}")
        out = {}
        for name, f in fields.items():
            where = f"{key}.{name}" if key else name
            if name not in raw:
                continue  # default
            v = self.value(hints[name], raw[name], where)
            check = f.metadata.get("check")
            if v is not None and check is not None and not check(v):
                self.fail(where, f"got {raw[name]!r}; allowed: {f.metadata['allowed']}")
            if v is not None and f.metadata.get("path"):
                v = self.resolve(v, where)
            out[name] = v
        return cls(**out)

    def resolve(self, p: str, key: str) -> str:
        path = Path(p)
        if not path.is_absolute() and self.base_dir is not None:
            path = self.base_dir / path
        if not path.is_file():
            self.fail(key, f"file not found: {path} (paths are relative to the YAML file)")
        return str(path.resolve())


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
    """Read, override and validate a scenario YAML. Raises ConfigError with a clear message."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: scenario file not found")
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
    return sc


def scenario_from_dict(raw: dict, base_dir: Path | None = None, source: str = "<dict>") -> Scenario:
    """Validate an in-memory mapping (tests, PettingZoo env)."""
    loader = _Loader(source, base_dir)
    sc = dataclasses.replace(loader.section(Scenario, raw, ""), source=source)
    _check_cross_fields(sc, loader)
    return sc


def _check_cross_fields(sc: Scenario, loader: _Loader) -> None:
    allowed = ENCODERS_BY_MODALITY[sc.perception.modality]
    if sc.perception.encoder not in allowed:
        loader.fail("perception.encoder",
                    f"{sc.perception.encoder!r} does not take {sc.perception.modality} input; "
                    f"allowed for modality {sc.perception.modality!r}: {', '.join(allowed)}")
    if sc.traffic.backend == "sumo" and sc.traffic.net is None:
        loader.fail("traffic.net", "required for backend 'sumo': a SUMO .net.xml relative to the YAML")
    if isinstance(sc.cavs.ego, tuple) and not sc.cavs.ego:
        loader.fail("cavs.ego", "an empty list; allowed: 'first', 'all' or a list of CAV ids")
    if sc.comm.drop.model == "gilbert_elliott" and sc.comm.drop.p_bg == 0 and sc.comm.drop.p_gb > 0:
        loader.fail("comm.drop.p_bg", "0 with p_gb > 0 never leaves the bad state; allowed: 0 < p_bg <= 1")
    if sc.comm.medium == "shared" and sc.comm.bandwidth_mbps is None and sc.comm.channel.model != "tr37885":
        loader.fail("comm.medium", "'shared' needs a data rate to share: set comm.bandwidth_mbps (e.g. 27) "
                    "or comm.channel.model tr37885 (the MCS rate)")
    if sc.comm.share.policy == "topk" and (sc.cavs.ego == "all" or (isinstance(sc.cavs.ego, tuple)
                                                                      and len(sc.cavs.ego) > 1)):
        loader.fail("comm.share.policy", "'topk' in a run needs one ego (cavs.ego: first or one id): an ego keeps "
                    "its whole map, so its broadcast cannot serve other egos; v2vsim.env scores every CAV as a "
                    "receiver")
    if not math.isfinite(sc.duration_s * sc.rate_hz):
        loader.fail("duration_s", f"{sc.duration_s:g} s at rate_hz {sc.rate_hz:g} is more frames than can be counted")
    _check_egos(sc, loader)
    _check_key_file(sc, loader)
    for name in ("listen", "connect"):
        for i, ep in enumerate(getattr(sc.transport, name)):
            _check_endpoint(ep, f"transport.{name}[{i}]", loader)


def _check_egos(sc: Scenario, loader: _Loader) -> None:
    """An ego id that is no CAV of the run would leave the run without an ego (nothing fused, no report);
    one listed twice would start two processes with the same name."""
    if not isinstance(sc.cavs.ego, tuple):
        return
    ids = [f"cav{i}" for i in range(sc.cavs.count)]  # v2vsim.traffic.base.cav_id
    allowed = ", ".join(ids) if len(ids) <= 4 else f"{ids[0]}..{ids[-1]}"
    for i, ego in enumerate(sc.cavs.ego):
        if ego not in ids:
            loader.fail(f"cavs.ego[{i}]", f"{ego!r} is not a CAV of this run (cavs.count is {sc.cavs.count}); "
                        f"allowed: {allowed}")
        if ego in sc.cavs.ego[:i]:
            loader.fail(f"cavs.ego[{i}]", f"{ego!r} is listed twice; each ego once")


def _check_key_file(sc: Scenario, loader: _Loader) -> None:
    """An empty key would turn signing on with a key anyone can sign with: refuse it here, in one line."""
    path = sc.comm.auth.key_file
    if path is None:
        return
    try:
        key = Path(path).read_bytes()
    except OSError as e:
        loader.fail("comm.auth.key_file", f"cannot read {path}: {e.strerror or e}")
    if not key.strip():  # the agents strip the key (agents/common.py read_key)
        loader.fail("comm.auth.key_file", f"{path} is empty or only whitespace; allowed: a file holding a secret key")


_ENDPOINT = re.compile(r"(?P<proto>[a-z][a-z0-9-]*)/(?P<addr>[^?#]+)(?:\?[^#]*)?(?:#.*)?")


def _check_endpoint(ep: str, key: str, loader: _Loader) -> None:
    """PROTO/HOST:PORT with a port zenoh and the OS accept (a bad one would otherwise surface as a
    traceback or a baffling zenoh error in a child process)."""
    m = _ENDPOINT.fullmatch(ep)
    if not m:
        loader.fail(key, f"got {ep!r}; allowed: a zenoh endpoint such as tcp/127.0.0.1:7447")
    if m.group("proto") in ("tcp", "udp", "tls", "quic", "ws"):
        host, sep, port = m.group("addr").rpartition(":")
        if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
            loader.fail(key, f"got {ep!r}; allowed: {m.group('proto')}/HOST:PORT with a port 1..65535")


def check_output_dir(path: Path, what: str) -> None:
    """Create `path` and prove a file can be written there, so that a bad --out or output.dir fails
    in one line before any process starts rather than in the ego at the end of the run."""
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{what} {path}: is a file, not a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path, prefix=".v2vsim-write-check-"):
            pass
    except OSError as e:
        raise ConfigError(f"{what} {path}: cannot write there: {(e.strerror or str(e)).lower()}") from None
