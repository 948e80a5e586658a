"""Checks across fields of a loaded scenario, and the output-directory check run before any process starts."""

from __future__ import annotations

import math
import re
import tempfile
from pathlib import Path

from models.registry import METHODS
from v2vsim.config.errors import ConfigError
from v2vsim.config.schema import Scenario
from v2vsim.config.schema_perception import ENCODERS_BY_MODALITY
from v2vsim.config.validate import _Loader


def _check_cross_fields(sc: Scenario, loader: _Loader) -> None:
    allowed = ENCODERS_BY_MODALITY[sc.perception.modality]
    if sc.perception.encoder not in allowed:
        loader.fail("perception.encoder",
                    f"{sc.perception.encoder!r} does not take {sc.perception.modality} input; "
                    f"allowed for modality {sc.perception.modality!r}: {', '.join(allowed)}")
    if sc.traffic.backend == "sumo" and sc.traffic.net is None:
        loader.fail("traffic.net", "required for backend 'sumo': a SUMO .net.xml relative to the YAML")
    if sc.traffic.hidden_foe is not None and sc.traffic.backend != "sumo":
        loader.fail("traffic.hidden_foe", "needs traffic.backend 'sumo' (the foe is placed on a SUMO junction); "
                    "allowed otherwise: null")
    if sc.traffic.standing and sc.traffic.backend != "sumo":
        loader.fail("traffic.standing", "needs traffic.backend 'sumo' (the vehicles stand in SUMO lanes); "
                    "allowed otherwise: []")
    if sc.traffic.hidden_stop is not None and sc.traffic.backend != "sumo":
        loader.fail("traffic.hidden_stop", "needs traffic.backend 'sumo' (it stands in a SUMO lane); allowed "
                    "otherwise: null")
    if sc.cavs.penetration is not None and sc.traffic.backend != "sumo":
        loader.fail("cavs.penetration", "needs traffic.backend 'sumo' (the vehicles that are not connected are "
                    "placed as SUMO vehicles); allowed otherwise: null")
    if len(sc.cavs.movements) > sc.cavs.count:
        loader.fail("cavs.movements", f"{len(sc.cavs.movements)} movements for {sc.cavs.count} CAVs; allowed: at "
                    f"most cavs.count")
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
    if sc.comm.fusion_deadline_ms is not None and sc.comm.fusion_deadline_ms >= 1000.0 / sc.rate_hz:
        loader.fail("comm.fusion_deadline_ms", f"{sc.comm.fusion_deadline_ms:g} ms is not less than one frame "
                    f"({1000.0 / sc.rate_hz:g} ms at rate_hz {sc.rate_hz:g}): frame k must be fused before frame k+1; "
                    f"allowed: 0 <= value < {1000.0 / sc.rate_hz:g}")
    if not math.isfinite(sc.duration_s * sc.rate_hz):
        loader.fail("duration_s", f"{sc.duration_s:g} s at rate_hz {sc.rate_hz:g} is more frames than can be counted")
    if sc.output.record_messages and sc.transport.clock != "lockstep":
        loader.fail("output.record_messages", "true needs transport.clock lockstep: in realtime what the ego has "
                    "at a frame depends on wall-clock arrival order, which a replay cannot reproduce")
    _check_egos(sc, loader)
    _check_fleet(sc, loader)
    _check_lies(sc, loader)
    _check_control(sc, loader)
    _check_key_file(sc, loader)
    for name in ("listen", "connect"):
        for i, ep in enumerate(getattr(sc.transport, name)):
            _check_endpoint(ep, f"transport.{name}[{i}]", loader)


def _cav_ids(sc: Scenario) -> tuple[list[str], str]:
    """The run's CAV ids (v2vsim.traffic.base.cav_id), and how an error lists them."""
    ids = [f"cav{i}" for i in range(sc.cavs.count)]
    return ids, ", ".join(ids) if len(ids) <= 4 else f"{ids[0]}..{ids[-1]}"


def _check_egos(sc: Scenario, loader: _Loader) -> None:
    """An ego id that is no CAV of the run would leave the run without an ego (nothing fused, no report);
    one listed twice would start two processes with the same name."""
    if not isinstance(sc.cavs.ego, tuple):
        return
    ids, allowed = _cav_ids(sc)
    for i, ego in enumerate(sc.cavs.ego):
        if ego not in ids:
            loader.fail(f"cavs.ego[{i}]", f"{ego!r} is not a CAV of this run (cavs.count is {sc.cavs.count}); "
                        f"allowed: {allowed}")
        if ego in sc.cavs.ego[:i]:
            loader.fail(f"cavs.ego[{i}]", f"{ego!r} is listed twice; each ego once")


def _check_lies(sc: Scenario, loader: _Loader) -> None:
    """A liar must be a CAV of the run (a typo would make an attacked run silently clean)."""
    ids, allowed = _cav_ids(sc)
    egos = sc.cavs.egos_among(ids)
    for i, lie in enumerate(sc.misbehaviour):
        for j, c in enumerate(lie.cavs):
            if c not in ids:
                loader.fail(f"misbehaviour[{i}].cavs[{j}]", f"{c!r} is not a CAV of this run (cavs.count is "
                            f"{sc.cavs.count}); allowed: {allowed}")
            if c in egos:
                loader.fail(f"misbehaviour[{i}].cavs[{j}]", f"{c!r} is an ego of this run: an ego fuses its own map, "
                            "so it would lie to itself; allowed: the CAVs that are not egos")
        if lie.kind == "remove_vehicle" and not lie.targets:
            loader.fail(f"misbehaviour[{i}].targets", "empty: remove_vehicle needs the ids of the actors it hides "
                        "(e.g. [foe0])")


def _check_fleet(sc: Scenario, loader: _Loader) -> None:
    """Each fleet group names CAVs of this run, each CAV in one group at most, an encoder of its modality; a fleet
    fuses in the LiDAR zoo's space (perception.encoder pointpillars, the base its types are aligned to)."""
    if not sc.cavs.fleet:
        return
    ids, allowed = _cav_ids(sc)
    if sc.perception.encoder != "pointpillars":
        loader.fail("cavs.fleet", f"a mixed fleet fuses in the LiDAR zoo's feature space, the base its agent types are "
                    f"aligned to (the `align` stage); perception.encoder is {sc.perception.encoder!r}; allowed: "
                    "perception.modality lidar with perception.encoder pointpillars")
    seen: dict[str, int] = {}
    for g, group in enumerate(sc.cavs.fleet):
        where = f"cavs.fleet[{g}]"
        if group.encoder not in ENCODERS_BY_MODALITY[group.modality]:
            loader.fail(f"{where}.encoder", f"{group.encoder!r} does not take {group.modality} input; allowed for "
                        f"modality {group.modality!r}: {', '.join(ENCODERS_BY_MODALITY[group.modality])}")
        for i, c in enumerate(group.cavs):
            if c not in ids:
                loader.fail(f"{where}.cavs[{i}]", f"{c!r} is not a CAV of this run (cavs.count is {sc.cavs.count}); "
                            f"allowed: {allowed}")
            if c in seen:
                loader.fail(f"{where}.cavs[{i}]", f"{c!r} is already in cavs.fleet[{seen[c]}]; each CAV in one group")
            seen[c] = g


def _check_control(sc: Scenario, loader: _Loader) -> None:
    """A closed loop needs SUMO (libsumo drives the vehicle), a method the run decodes, and a delay the lockstep
    pipeline can honour (the driver steps frame k + pipeline + 1 once the ego acked frame k)."""
    c = sc.control
    if c is None:
        return
    if sc.traffic.backend != "sumo":
        loader.fail("control", f"needs traffic.backend 'sumo' (libsumo drives the vehicle); got "
                    f"{sc.traffic.backend!r}: remove the control section for an open-loop run")
    if c.perceive == "driving" and c.method != "oracle" and c.method not in METHODS:
        loader.fail("control.method", f"{c.method!r} is no fusion method; allowed: oracle, {', '.join(METHODS)}")
    if c.perceive == "all" and c.method != "oracle" and c.method not in sc.perception.methods:
        loader.fail("control.method", f"{c.method!r} is not among perception.methods "
                    f"({', '.join(sc.perception.methods)}); allowed: oracle or one of those")
    d = c.actuation_delay_frames
    if d is not None and sc.transport.clock == "realtime":
        loader.fail("control.actuation_delay_frames", "must be null under transport.clock realtime: the newest plan "
                    "that arrived is applied at each step, so the delay is what the wall clock gives")
    if d is not None and d < sc.transport.pipeline:
        loader.fail("control.actuation_delay_frames", f"{d} is less than transport.pipeline ({sc.transport.pipeline}): "
                    "the driver steps that far ahead of the ego's plans; allowed: an integer >= "
                    f"{sc.transport.pipeline}, or null")


def _check_key_file(sc: Scenario, loader: _Loader) -> None:
    """An empty key would turn signing on with a key anyone can sign with: refuse it here, in one line."""
    path = sc.comm.auth.key_file
    if path is not None and sc.comm.auth.identity == "per_process":
        loader.fail("comm.auth", "key_file and identity: per_process are two ways to sign; choose one "
                    "(per_process: each process signs as itself; key_file: one shared key)")
    if path is None:
        return
    try:
        key = Path(path).read_bytes()
    except OSError as e:
        loader.fail("comm.auth.key_file", f"cannot read {path}: {e.strerror or e}")
    if not key.strip():  # the agents strip the key (agents/args.py read_key)
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


def check_plugins(sc: Scenario) -> None:
    """The fusion plugins among perception.methods (models.registry), each imported and checked against the fusion
    contract (and no installed plugin claiming a requested built-in's name); ConfigError with the plugin's error
    (one line: the entry point, the object it points at, what it broke) when one cannot be used. Not part of
    loading a scenario, which every process does (a plugin imports torch): the runner (check_scenario), `v2vsim
    sweep` and the env call it before anything starts."""
    from models.registration import PluginError
    from models.registry import check_methods

    try:
        check_methods(sc.perception.methods)
    except PluginError as e:
        raise ConfigError(f"{sc.source}: perception.methods: {e}") from None


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
