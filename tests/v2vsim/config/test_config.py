"""Scenario YAML: defaults, overrides and the errors a user sees (file, key path, what is allowed)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from v2vsim.config import ConfigError, load_scenario

REPO = Path(__file__).resolve().parents[3]
INTERSECTION = REPO / "scenarios" / "intersection.yaml"


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "s.yaml"
    p.write_text(text)
    return p


def test_defaults_and_immutability(tmp_path: Path) -> None:
    sc = load_scenario(_write(tmp_path, "traffic: {backend: highway-env}\n"))
    assert sc.seed == 0 and sc.rate_hz == 10 and sc.frames == 200
    assert sc.cavs.count == 4 and sc.bev.cells == 256 and sc.comm.bandwidth_mbps == 27
    assert sc.sensors.lidar.vertical_fov_deg == (-25.0, 5.0)
    assert sc.perception.methods[-1] == "cobevt"
    assert sc.cavs.arrival_s == (0.0, 4.0) and sc.cavs.meet.neighbours == 2 and sc.cavs.meet.share == 0.9
    with pytest.raises(AttributeError, match=r"cannot assign to field 'seed'"):
        sc.seed = 3  # type: ignore[misc]


def test_override_parses_yaml_scalars(tmp_path: Path) -> None:
    p = _write(tmp_path, "traffic: {backend: highway-env}\n")
    sc = load_scenario(p, ["comm.drop.p=0.3", "comm.bandwidth_mbps=null", "perception.methods=[none, cobevt]",
                           "output.rerun=false"])
    assert sc.comm.drop.p == 0.3 and sc.comm.bandwidth_mbps is None
    assert sc.perception.methods == ("none", "cobevt") and sc.output.rerun is False


@pytest.mark.parametrize(
    ("text", "overrides", "expect"),
    [
        ("cavs: {count: 0}\n", [], ["cavs.count", "1..16"]),
        ("cavs: {arrival_s: [5, 1]}\n", [], ["cavs.arrival_s", "lo <= hi"]),
        ("cavs: {arrival_s: [-1, 1]}\n", [], ["cavs.arrival_s", "0 <= lo"]),
        ("cavs: {arrival_s: 3}\n", [], ["cavs.arrival_s", "a list of a number (2 items)"]),
        ("cavs: {meet: {share: 1.5}}\n", [], ["cavs.meet.share", "0..1"]),
        ("cavs: {meet: {trials: 0}}\n", [], ["cavs.meet.trials", "1..200"]),
        ("cavs: {meet: {neigbours: 2}}\n", [], ["cavs.meet.neigbours", "did you mean 'neighbours'"]),
        ("seed: 1\n", ["cavs.arrival_s=[1]"], ["cavs.arrival_s", "got 1 items"]),
        ("comm: {latency_ms: {mean: -5}}\n", [], ["comm.latency_ms.mean", ">= 0"]),
        ("comm: {drop: {p: 1.5}}\n", [], ["comm.drop.p", "0..1"]),
        ("comm: {dorp: {p: 0.1}}\n", [], ["comm.dorp", "did you mean 'drop'"]),
        ("sensors: {lidar: {chanels: 16}}\n", [], ["sensors.lidar.chanels", "did you mean 'channels'"]),
        ("seed: abc\n", [], ["seed", "integer"]),
        ("rate_hz: [1]\n", [], ["rate_hz", "number"]),
        ("traffic: {backend: carla}\n", [], ["traffic.backend", "'sumo' | 'highway-env'"]),
        ("traffic: {backend: sumo, net: missing.net.xml}\n", [], ["traffic.net", "file not found"]),
        ("perception: {modality: camera}\n", [], ["perception.encoder", "sinbevt, lara"]),
        ("seed: 1\n", ["comm.drop.p=2"], ["comm.drop.p", "0..1"]),
        ("seed: 1\n", ["comm.nope=1"], ["comm.nope", "unknown key"]),
        ("seed: [1\n", [], ["not valid YAML", "line"]),
        # issue 8: values that passed the range checks and crashed later, and a key given twice
        ("duration_s: .inf\n", [], ["duration_s", "finite"]),
        ("duration_s: .nan\n", [], ["duration_s", "finite"]),
        ("duration_s: -1\n", [], ["duration_s", "> 0"]),
        ("rate_hz: -.inf\n", [], ["rate_hz", "finite"]),
        ("duration_s: 1.0e+308\n", [], ["duration_s", "more frames than can be counted"]),
        ("seed: 2147483648\n", [], ["seed", "0..2147483647"]),
        ("seed: -1\n", [], ["seed", "0..2147483647"]),
        ("seed: 1\n", ["seed=4294967296"], ["seed", "0..2147483647"]),
        ("transport: {listen: ['tcp/127.0.0.1:65536']}\n", [], ["transport.listen[0]", "1..65535"]),
        ("transport: {connect: ['tcp/127.0.0.1:99999']}\n", [], ["transport.connect[0]", "1..65535"]),
        ("transport: {connect: [localhost]}\n", [], ["transport.connect[0]", "zenoh endpoint"]),
        ("seed: 1\nrate_hz: 5\nseed: 2\n", [], ["duplicate key 'seed'", "line 4", "first at line 2"]),
        ("comm: {drop: {p: 0.1, p: 0.2}}\n", [], ["duplicate key 'p'", "line 2"]),
        # issue 7: an ego that is no CAV of the run, or one listed twice
        ("seed: 1\n", ["cavs.ego=[cav9]"], ["cavs.ego[0]", "'cav9'", "cavs.count is 4", "cav0, cav1, cav2, cav3"]),
        ("cavs: {count: 2, ego: [cav1, cav2]}\n", [], ["cavs.ego[1]", "'cav2'", "cav0, cav1"]),
        ("seed: 1\n", ["cavs.ego=[cav0,cav0]"], ["cavs.ego[1]", "'cav0' is listed twice"]),
        ("- a\n- b\n", [], ["top level must be a mapping"]),
        # issue 29: the fusion deadline lies within the frame
        ("seed: 1\n", ["comm.fusion_deadline_ms=100"], ["comm.fusion_deadline_ms", "not less than one frame",
                                                         "0 <= value < 100"]),
        ("rate_hz: 20\n", ["comm.fusion_deadline_ms=60"], ["comm.fusion_deadline_ms", "0 <= value < 50"]),
        ("seed: 1\n", ["comm.fusion_deadline_ms=-1"], ["comm.fusion_deadline_ms", ">= 0"]),
        ("seed: 1\n", ["comm.compensation=maybe"], ["comm.compensation", "true/false"]),
        # issue 48: a mixed fleet names CAVs of the run once each, an encoder of its modality, on the LiDAR base
        ("seed: 1\n", ["cavs.fleet=[{cavs: [cav7]}]"], ["cavs.fleet[0].cavs[0]", "'cav7'", "cavs.count is 4"]),
        ("seed: 1\n", ["cavs.fleet=[{cavs: [cav1]}, {cavs: [cav2, cav1]}]"],
         ["cavs.fleet[1].cavs[1]", "already in cavs.fleet[0]"]),
        ("seed: 1\n", ["cavs.fleet=[{cavs: [cav1], modality: camera, encoder: pointpillars}]"],
         ["cavs.fleet[0].encoder", "sinbevt, lara"]),
        ("seed: 1\n", ["cavs.fleet=[{cavs: []}]"], ["cavs.fleet[0].cavs", "non-empty list"]),
        ("seed: 1\n", ["cavs.fleet=[{cavs: [cav1], sensor: camera}]"], ["cavs.fleet[0].sensor", "unknown key"]),
        ("perception: {modality: camera, encoder: sinbevt}\n", ["cavs.fleet=[{cavs: [cav1]}]"],
         ["cavs.fleet", "LiDAR zoo's feature space", "pointpillars"]),
    ],
)
def test_bad_input_names_file_key_and_allowed(tmp_path: Path, text: str, overrides: list[str],
                                              expect: list[str]) -> None:
    p = _write(tmp_path, "traffic: {backend: highway-env}\n" + text if "traffic" not in text and "- a" not in text
               else text)
    with pytest.raises(ConfigError) as e:
        load_scenario(p, overrides)
    msg = str(e.value)
    assert str(p) in msg
    for part in expect:
        assert part in msg, msg


def test_duplicate_key_in_a_set_value() -> None:
    with pytest.raises(ConfigError, match="--set comm.latency_ms=.*duplicate key 'mean'"):
        load_scenario(INTERSECTION, ["comm.latency_ms={mean: 1, mean: 2}"])


def test_two_egos_in_range_load(tmp_path: Path) -> None:
    sc = load_scenario(_write(tmp_path, "traffic: {backend: highway-env}\n"), ["cavs.count=3", "cavs.ego=[cav2, cav0]"])
    assert sc.cavs.ego == ("cav2", "cav0")


def test_merge_keys_are_not_duplicates(tmp_path: Path) -> None:
    text = "traffic: {backend: highway-env}\nx: &d {mean: 5}\n"
    with pytest.raises(ConfigError, match="unknown key"):  # the anchor parses; only the stray key is refused
        load_scenario(_write(tmp_path, text))
    merged = "traffic: {backend: highway-env}\ncomm:\n  latency_ms: {<<: {mean: 5}, mean: 7}\n"
    sc = load_scenario(_write(tmp_path, merged))
    assert sc.comm.latency_ms.mean == 7


@pytest.mark.parametrize("content", [b"", b"\n", b"  \t\r\n  \n"])
def test_empty_or_blank_key_file_is_refused(tmp_path: Path, content: bytes) -> None:
    """issue 8 item 4: an empty key would turn signing on with a key anyone can sign with."""
    key = tmp_path / "v2v.key"
    key.write_bytes(content)
    p = _write(tmp_path, "traffic: {backend: highway-env}\ncomm: {auth: {key_file: v2v.key}}\n")
    with pytest.raises(ConfigError) as e:
        load_scenario(p)
    msg = str(e.value)
    assert "comm.auth.key_file" in msg and str(key) in msg and "empty or only whitespace" in msg
    key.write_bytes(b"  a secret\n")
    assert load_scenario(p).comm.auth.key_file == str(key)


def test_missing_or_unreadable_key_file_is_refused(tmp_path: Path) -> None:
    p = _write(tmp_path, "traffic: {backend: highway-env}\ncomm: {auth: {key_file: nope.key}}\n")
    with pytest.raises(ConfigError, match=r"comm\.auth\.key_file: file not found"):
        load_scenario(p)
    (tmp_path / "dir.key").mkdir()
    with pytest.raises(ConfigError, match=r"comm\.auth\.key_file: file not found"):
        load_scenario(p, ["comm.auth.key_file=dir.key"])
    if os.geteuid() != 0:  # root reads anything
        key = tmp_path / "locked.key"
        key.write_text("secret")
        key.chmod(0)
        with pytest.raises(ConfigError, match=r"comm\.auth\.key_file: cannot read"):
            load_scenario(p, ["comm.auth.key_file=locked.key"])


def test_binary_scenario_file(tmp_path: Path) -> None:
    p = tmp_path / "s.yaml"
    p.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe")
    with pytest.raises(ConfigError, match="not a text \\(UTF-8\\) file"):
        load_scenario(p)
    p.write_bytes(b"seed: 1\x00\x01\n")  # valid UTF-8, but not YAML
    with pytest.raises(ConfigError, match="not valid YAML") as e:
        load_scenario(p)
    assert "\n" not in str(e.value)


def test_missing_scenario_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_scenario(tmp_path / "nope.yaml")


def test_cli_bad_yaml_exits_2_without_traceback(tmp_path: Path) -> None:
    p = _write(tmp_path, "cavs: {count: 99}\n")
    r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "frame", str(p), "--at", "1", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert "cavs.count" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "run", str(INTERSECTION), "--set", "comm.drop.p=7"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "comm.drop.p" in r.stderr and "Traceback" not in r.stderr


def test_shipped_scenarios_load() -> None:
    """Every shipped scenario loads, names itself after its file (no default name slipped in) and has a network."""
    paths = sorted((REPO / "scenarios").glob("*.yaml"))
    assert len(paths) >= 8, "the shipped scenarios went missing"
    for path in paths:
        sc = load_scenario(path)
        assert sc.name == path.stem, f"{path.name}: name {sc.name!r}"


def test_share_topk_needs_one_ego_in_a_run() -> None:
    load_scenario("scenarios/intersection.yaml", ["comm.share.policy=topk", "comm.share.fraction=0.2"])
    with pytest.raises(ConfigError, match="comm.share.policy"):
        load_scenario("scenarios/intersection.yaml", ["comm.share.policy=topk", "cavs.ego=all"])
    with pytest.raises(ConfigError, match="comm.share.fraction"):
        load_scenario("scenarios/intersection.yaml", ["comm.share.fraction=1.5"])


def test_the_fusion_deadline_defaults_to_half_a_frame(tmp_path: Path) -> None:
    sc = load_scenario(_write(tmp_path, "traffic: {backend: highway-env}\n"))
    assert sc.comm.fusion_deadline_ms is None and sc.fusion_deadline_s == pytest.approx(0.05)  # 10 Hz
    fast = load_scenario(_write(tmp_path, "traffic: {backend: highway-env}\nrate_hz: 1000\n"))
    assert fast.fusion_deadline_s == pytest.approx(0.0005)
    assert load_scenario(_write(tmp_path, "traffic: {backend: highway-env}\n"), ["comm.fusion_deadline_ms=0"]
                         ).fusion_deadline_s == 0.0


def test_trust_is_on_by_default_and_off_is_spelled_plainly(tmp_path: Path) -> None:
    """Issue 45: per-process identities unless the scenario says otherwise; a shared key_file resolves `auto` to
    the shared key; a bare YAML `off` (a boolean to YAML 1.1) is the mode `off`, in the file and in --set."""
    base = "traffic: {backend: highway-env}\n"
    sc = load_scenario(_write(tmp_path, base))
    assert sc.comm.auth.identity == "per_process" and sc.comm.auth.mode == "per_process"
    assert load_scenario(_write(tmp_path, base + "comm: {auth: {identity: off}}\n")).comm.auth.mode == "off"
    assert load_scenario(_write(tmp_path, base), ["comm.auth.identity=off"]).comm.auth.mode == "off"
    (tmp_path / "v2v.key").write_text("a secret\n")
    sc = load_scenario(_write(tmp_path, base + "comm: {auth: {key_file: v2v.key}}\n"))
    assert sc.comm.auth.identity == "off" and sc.comm.auth.mode == "shared_key"
    with pytest.raises(ConfigError, match="two ways to sign"):
        load_scenario(_write(tmp_path, base + "comm: {auth: {key_file: v2v.key, identity: per_process}}\n"))
    with pytest.raises(ConfigError, match=r"comm\.auth\.identity: got 'of'.*did you mean 'off'"):
        load_scenario(_write(tmp_path, base), ["comm.auth.identity=of"])
