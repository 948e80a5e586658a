"""agents.ego_defence.SenderCheck on hand-made late-fusion outputs (no model runs): what the defence leaves out of
a frame, flagged senders and, with `defence.unjudged: exclude`, the senders it had no evidence on."""

from __future__ import annotations

import numpy as np

from agents.ego_defence import SenderCheck
from v2vsim.config.load import load_scenario
from v2vsim.perception.fuse import FusionInputs

CELLS, SIZE = 100, 100.0


def _road() -> np.ndarray:
    c = SIZE / 2 - (np.arange(CELLS) + 0.5)
    fwd, left = c[:, None], c[None, :]
    return (np.abs(left) < 4) | ((fwd > 10) & (fwd < 18))


def _inp() -> FusionInputs:
    honest = np.zeros((3, CELLS, CELLS), np.float32)
    honest[1] = _road()
    liar = np.zeros_like(honest)  # no road anywhere: a zeroed map
    none = np.zeros((0, 6), np.float32)
    poses = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 95.0, 0]], np.float32)  # cav3 far off to the left
    return FusionInputs(senders=["cav0", "cav1", "cav2", "cav3"], rel_poses=poses,
                        outputs={"cav0": (honest, none), "cav1": (honest.copy(), none), "cav2": (liar, none),
                                 "cav3": (honest.copy(), none)})


def _check(*sets: str) -> tuple[FusionInputs, set[str], SenderCheck]:
    sc = load_scenario("scenarios/t_junction.yaml", ["bev.size_m=100", *sets])
    check = SenderCheck(sc, model=None)  # type: ignore[arg-type]  # outputs only: nothing to decode
    out, flagged = check.check(0, _inp(), road_map=_road())
    return out, flagged, check


def test_the_defence_leaves_out_the_flagged_sender_and_keeps_the_unjudged_one_by_default() -> None:
    out, flagged, check = _check("defence.exclude=true")
    assert flagged == {"cav2"} and set(out.outputs) == {"cav0", "cav1", "cav3"}
    assert "cav3" not in check.frames  # too far to share a cell: not judged


def test_unjudged_exclude_also_leaves_out_a_sender_it_has_no_evidence_on() -> None:
    out, flagged, check = _check("defence.exclude=true", "defence.unjudged=exclude")
    assert flagged == {"cav2"} and set(out.outputs) == {"cav0", "cav1"}
    assert check.to_json()["excluded_unjudged_sender_frames"] == 1 and check.to_json()["excluded_sender_frames"] == 1


def test_detection_alone_changes_nothing_fused() -> None:
    out, flagged, _ = _check("defence.detect=true", "defence.unjudged=exclude")
    assert flagged == {"cav2"} and set(out.outputs) == {"cav0", "cav1", "cav2", "cav3"}


def _honest_inp() -> FusionInputs:
    inp = _inp()
    inp.outputs["cav2"] = (inp.outputs["cav1"][0].copy(), inp.outputs["cav1"][1])  # cav2 tells the truth now
    return inp


def test_remember_keeps_a_caught_liar_out_after_it_stops_lying_until_it_has_earned_its_way_back() -> None:
    sc = load_scenario("scenarios/t_junction.yaml", ["bev.size_m=100", "defence.exclude=true",
                                                     "defence.remember=true"])
    check = SenderCheck(sc, model=None)  # type: ignore[arg-type]
    out, flagged = check.check(0, _inp(), road_map=_road())
    assert flagged == {"cav2"} and "cav2" not in out.outputs
    fused = []
    for k in range(1, 12):  # honest from frame 1 on: judged and clean each frame
        out, flagged = check.check(k, _honest_inp(), road_map=_road())
        assert not flagged
        fused.append("cav2" in out.outputs)
    assert fused == [False] * 7 + [True] * 4  # out for 7 more frames: back at the 8th clean one
    rep = check.to_json()["reputation"]
    assert rep["senders"]["cav2"]["frames_untrusted"] == 8 and rep["excluded_untrusted_sender_frames"] == 7
    assert rep["senders"]["cav1"]["frames_untrusted"] == 0
    # without remember, the same liar is fused again at the first honest frame
    forgetful = SenderCheck(load_scenario("scenarios/t_junction.yaml", ["bev.size_m=100", "defence.exclude=true"]),
                            model=None)  # type: ignore[arg-type]
    forgetful.check(0, _inp(), road_map=_road())
    assert "cav2" in forgetful.check(1, _honest_inp(), road_map=_road())[0].outputs


def _phantom_inp() -> FusionInputs:
    """cav2 claims a car 20 m ahead on the road where the ego's rays pass freely (128 x 128 evidence)."""
    from v2vsim.perception.evidence import FREE, UNKNOWN

    inp = _honest_inp()
    maps = inp.outputs["cav2"][0].copy()
    c = SIZE / CELLS
    rows, cols = slice(int((SIZE / 2 - 22.3) // c), int((SIZE / 2 - 17.7) // c) + 1), slice(49, 51)  # x 18-22, |y| < 1
    maps[0, rows, cols] = 1.0
    inp.outputs["cav2"] = (maps, inp.outputs["cav2"][1])
    e = 128
    seen = np.full((e, e), UNKNOWN, np.uint8)
    ce = SIZE / e
    seen[int((SIZE / 2 - 40) // ce):int(SIZE / 2 // ce), int((SIZE / 2 - 3) // ce):int((SIZE / 2 + 3) // ce)] = FREE
    blind = np.full((e, e), UNKNOWN, np.uint8)
    inp.evidence = {"cav0": seen, "cav1": blind, "cav2": blind.copy()}
    return inp


def test_evidence_flags_a_phantom_only_where_a_threshold_is_set() -> None:
    base = ["bev.size_m=100", "defence.exclude=true", "defence.evidence=true"]
    judged = SenderCheck(load_scenario("scenarios/t_junction.yaml", [*base, "defence.phantom_threshold_m2=4"]),
                         model=None)  # type: ignore[arg-type]
    out, flagged = judged.check(0, _phantom_inp(), road_map=_road())
    assert flagged == {"cav2"} and "cav2" not in out.outputs
    row = judged.to_json()["evidence"]["cav2"]["per_frame"][0]
    assert row[1] > 4 and row[9] is True
    unset = [f"defence.{k}=null" for k in ("phantom_threshold_m2", "removed_threshold_m2", "unclaimed_threshold_m2",
                                           "pose_gain_threshold", "later_threshold_m2")]
    recorded = SenderCheck(load_scenario("scenarios/t_junction.yaml", [*base, *unset]),
                           model=None)  # type: ignore[arg-type]
    out, flagged = recorded.check(0, _phantom_inp(), road_map=_road())
    assert not flagged and "cav2" in out.outputs  # no threshold: recorded, not judged
    assert recorded.to_json()["evidence"]["cav2"]["max_phantom_m2"] > 4


def test_the_check_reuses_nones_map_of_the_ego_and_it_is_what_decoding_again_gives() -> None:
    """The ego's own map comes from the `none` prediction (decoded once, agents/ego.py) and equals decode_alone's."""
    from v2vsim.perception.build import build_agent_encoder, build_method_models
    from v2vsim.perception.consistency import decode_alone
    from v2vsim.perception.fuse import predict
    from v2vsim.perception.plan import plan_models

    sc = load_scenario("scenarios/t_junction_occluded.yaml", ["defence.detect=true"])
    plan = plan_models(sc)
    model = build_method_models(plan, build_agent_encoder(plan), ("none",))["none"].eval()
    rng = np.random.default_rng(0)
    feats = {s: rng.standard_normal((64, 64, 64)).astype(np.float32) for s in ("cav0", "cav1", "cav2")}
    inp = FusionInputs(senders=list(feats), rel_poses=np.zeros((3, 3), np.float32), features=feats)
    own = predict("none", model, inp, sc.bev.cells)
    check = SenderCheck(sc, model)
    calls: list[list[str]] = []
    real = check.model.heads.segmentation

    def counted(x):  # type: ignore[no-untyped-def]
        calls.append([x.shape[0]])
        return real(x)

    check.model.heads.segmentation = counted  # type: ignore[method-assign]
    reused = check._decoded(feats, "cav0", own)
    assert calls == [[2]]  # the two senders only: the ego's map was not decoded again
    again = decode_alone(model, feats)
    for s in feats:
        assert np.allclose(reused[s], again[s], atol=1e-5)


def test_a_small_pose_lie_adds_up_over_frames_and_an_honest_senders_small_gains_do_not(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """defence.pose_cusum_*: cav2's pose gain 0.2 a frame (under pose_gain_threshold 0.32) sums past the threshold
    0.11 at its third frame (0.04, 0.08, 0.12 with drift 0.16); cav1's 0.1 a frame (under the drift) never adds up.
    pose_check stubbed: this is the sum's test, not the wall matching's (tests/v2vsim/perception)."""
    import agents.ego_defence as ed
    from v2vsim.perception.evidence import UNKNOWN
    from v2vsim.perception.evidence_check import PoseVerdict

    gains = {1: 0.1, 2: 0.2, 3: 0.0}
    calls = iter([1, 2, 3] * 10)
    monkeypatch.setattr(ed, "pose_check", lambda *a, **k: PoseVerdict(0.8, -2.0, 0.5, 0.5 + gains[next(calls)], 100))
    sc = load_scenario("scenarios/t_junction.yaml", ["bev.size_m=100", "defence.evidence=true"])
    check = SenderCheck(sc, model=None)  # type: ignore[arg-type]
    flagged_at = []
    for k in range(5):
        inp = _honest_inp()
        inp.evidence = {s: np.full((128, 128), UNKNOWN, np.uint8) for s in inp.senders}
        _, flagged = check.check(k, inp, road_map=_road(), buildings=np.zeros((128, 128), bool))
        flagged_at.append(sorted(flagged))
    assert flagged_at == [[], [], ["cav2"], ["cav2"], ["cav2"]]
    rows = check.to_json()["evidence"]
    assert [r[13] for r in rows["cav2"]["per_frame"]] == [0.04, 0.08, 0.12, 0.16, 0.2]
    assert all(r[13] == 0.0 for r in rows["cav1"]["per_frame"])


def test_a_caught_liar_is_left_out_of_the_witnesses_so_its_garbage_does_not_frame_an_honest_sender() -> None:
    """cav2 claims vehicles everywhere (as features x 8 decode) and its rays stop in the area behind the ego that
    honest cav1's rays pass freely: judged with cav2 among the witnesses, cav1 would have "removed" 120 m^2 of cars.
    cav2's phantom over the ego's free road is the larger excess, so it is left out and cav1 judged again: clean."""
    from v2vsim.perception.evidence import FREE, OCCUPIED, UNKNOWN

    inp = _honest_inp()
    maps = inp.outputs["cav2"][0].copy()
    maps[0] = 1.0  # a vehicle in every cell
    inp.outputs["cav2"] = (maps, inp.outputs["cav2"][1])
    e, ce = 128, SIZE / 128

    def band(x0: float, x1: float, value: int) -> np.ndarray:  # x0..x1 m forward, |y| < 3 m, in its own frame
        g = np.full((e, e), UNKNOWN, np.uint8)
        g[int((SIZE / 2 - x1) // ce):int((SIZE / 2 - x0) // ce), int((SIZE / 2 - 3) // ce):int((SIZE / 2 + 3) // ce)] \
            = value
        return g

    inp.evidence = {"cav0": band(0, 40, FREE), "cav1": band(-20, 0, FREE), "cav2": band(-20, 0, OCCUPIED)}
    sc = load_scenario("scenarios/t_junction.yaml", ["bev.size_m=100", "defence.evidence=true"])
    check = SenderCheck(sc, model=None)  # type: ignore[arg-type]
    _, flagged = check.check(0, inp, road_map=_road())
    assert flagged == {"cav2"}
    rows = check.to_json()["evidence"]
    assert rows["cav2"]["per_frame"][0][1] > 9.91 and rows["cav1"]["per_frame"][0][2] == 0.0
