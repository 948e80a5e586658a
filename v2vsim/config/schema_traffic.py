"""The scenario schema's `traffic` and `cavs` sections (DESIGN.md "Scenario YAML"): who is on the road, the
background traffic and the vehicles placed in it, and which CAVs take part, fuse and drive."""

from __future__ import annotations

import typing
from dataclasses import dataclass, field
from typing import Literal

from v2vsim.config.schema_fields import _f, _nonneg, _pos, _prob


@dataclass(frozen=True)
class HiddenFoeConfig:
    """One extra main-road vehicle, foe0, that buildings hide from the ego (v2vsim/traffic/sumo_hidden_foe.py): it
    reaches the main junction `arrival_offset_s` (drawn per seed) after the ego's free-flow arrival at its stop line.
    attentive false: it does not brake for a vehicle already in the junction (SUMO's priority-road drivers do)."""

    arrival_offset_s: tuple[float, float] = _f((0.5, 2.5), "[lo, hi] with -10 <= lo <= hi <= 10 (seconds after the "
                                               "ego's free-flow arrival at its stop line)",
                                               lambda v: -10 <= v[0] <= v[1] <= 10)
    attentive: bool = False
    # auto: the main-road arm that buildings hide from the ego; opposite: oncoming traffic (an ego turning left)
    side: Literal["auto", "left", "right", "opposite"] = "auto"
    # its free-flow speed: null = the lane's speed limit; a benchmark grid's second factor (as Coopernaut's)
    speed_mps: float | None = _f(None, "0 < v <= 40 (m/s) or null (the lane's speed limit)",
                                 lambda v: 0 < v <= 40)
    # true: it drives through a red light (SUMO's junctionModel.jmDriveAfterRedTime), a red-light runner at a
    # signalised junction where the ego has green (scenarios/red_light_runner.yaml)
    runs_red: bool = False


@dataclass(frozen=True)
class StandingVehicle:
    """A vehicle that stands in a lane for the whole run (v2vsim/traffic/sumo_standing.py): a truck queued to turn
    left, a parked van, a broken-down car. It is there from the start of the warm-up; traffic behind it queues or
    changes lane. Its type's extents (car 4.5 x 1.9 x 1.5 m, van 5.4 x 2.0 x 2.4, truck 8.5 x 2.5 x 3.4) make it an
    occluder for LiDAR and cameras as any vehicle is."""

    edge: str = _f("", "an edge id of traffic.net", lambda v: bool(v))
    lane: int = _f(0, ">= 0 (lane index on the edge, 0 = its rightmost)", _nonneg)
    to_end_m: float = _f(0.5, ">= 0 (m from its front bumper to the lane's end: 0.5 = at the stop line)", _nonneg)
    type: Literal["car", "van", "truck", "bus"] = "truck"


@dataclass(frozen=True)
class HiddenStopConfig:
    """A vehicle standing in the ego's exit lane just past the main junction (v2vsim/traffic/sumo_standing.py
    insert_hidden_stop): a lead vehicle stopped around a blind corner (NHTSA "lead vehicle stopped"). It is
    inserted with the CAVs, `distance_m` from the start of the lane the ego leaves the junction by (its rear), and
    drives off `until_s` after frame 0."""

    distance_m: float = _f(10.0, ">= 0 (m from the start of the ego's exit lane to its rear bumper)", _nonneg)
    until_s: float = _f(15.0, "> 0 (s after frame 0 at which it drives off)", _pos)
    type: Literal["car", "van", "truck", "bus"] = "car"


@dataclass(frozen=True)
class VehicleMix:
    """The background traffic's classes (SUMO vTypes with their extents, v2vsim/traffic/sumo.py: car 4.5 x 1.9 x
    1.5 m, van 5.4 x 2.0 x 2.4, truck 8.5 x 2.5 x 3.4, bus 12.0 x 2.55 x 3.2), as shares of the vehicles entering.
    The default is the mix every shipped scenario was calibrated with; the generated towns vary it."""

    car: float = _f(0.80, ">= 0 (share)", _nonneg)
    van: float = _f(0.12, ">= 0 (share)", _nonneg)
    truck: float = _f(0.08, ">= 0 (share)", _nonneg)
    bus: float = _f(0.0, ">= 0 (share)", _nonneg)

    def shares(self) -> tuple[tuple[str, float], ...]:
        """(vType, share) of the classes with a share above 0, normalised to sum to 1 (the default's three as
        written: 0.8 + 0.12 + 0.08 is exactly 1.0, so the shipped scenarios draw as they always did)."""
        items = [(k, float(getattr(self, k))) for k in ("car", "van", "truck", "bus") if getattr(self, k) > 0]
        total = sum(v for _, v in items)
        return tuple((k, v / total) for k, v in items) if total != 1.0 else tuple(items)


@dataclass(frozen=True)
class TrafficConfig:
    backend: Literal["sumo", "highway-env"] = "sumo"
    net: str | None = _f(None, "path to a SUMO .net.xml, relative to the YAML", path="file?")
    buildings: str | None = _f(None, "path to a SUMO .poly.xml, relative to the YAML", path="file?")
    background_per_hour: float = _f(900.0, ">= 0", _nonneg)
    warmup_s: float = _f(10.0, ">= 0 (background traffic runs this long before frame 0)", _nonneg)
    building_height_m: tuple[float, float] = _f((8.0, 15.0), "[lo, hi] with 0 < lo <= hi",
                                                lambda v: 0 < v[0] <= v[1])
    hidden_foe: HiddenFoeConfig | None = None  # null: no foe (SUMO backend only)
    standing: tuple[StandingVehicle, ...] = ()  # vehicles standing in a lane all run (SUMO backend only)
    vehicle_mix: VehicleMix = field(default_factory=VehicleMix)  # the background's classes (SUMO backend only)
    hidden_stop: HiddenStopConfig | None = None  # null: none (SUMO backend only)


@dataclass(frozen=True)
class MeetConfig:
    """What CAV placement aims for (see v2vsim/traffic/sumo.py): at least `neighbours` other CAVs
    within comm.range_m of the first ego in at least `share` of the frames, counted from frame 0 over the first
    `horizon_s` seconds (null: the whole run)."""

    neighbours: int = _f(2, ">= 0 (capped at cavs.count - 1)", _nonneg)
    share: float = _f(0.9, "0..1", _prob)
    trials: int = _f(24, "1..200 (candidate placements simulated ahead; 1 = the first candidate only)",
                     lambda v: 1 <= v <= 200)
    # why: a closed-loop run's duration is its time limit; the cast (where the CAVs start) must not change when
    # only the time limit does, so the look-ahead can span the encounter rather than the whole run
    horizon_s: float | None = _f(None, "> 0 (s) or null (duration_s): the frames the look-ahead scores", _pos)

    def frames(self, duration_frames: int, rate_hz: float) -> int:
        """The frames placement scores: the run's, or the first horizon_s seconds of them."""
        if self.horizon_s is None:
            return duration_frames
        return max(1, min(duration_frames, round(self.horizon_s * rate_hz)))


@dataclass(frozen=True)
class FleetGroup:
    """CAVs that carry another sensor and encoder than perception.modality / perception.encoder (a mixed fleet,
    docs/scenario.md): their features join the run's feature space through an encoder aligned to it (the
    `align` training stage, HEAL's backward alignment)."""

    cavs: tuple[str, ...] = _f((), "a non-empty list of CAV ids (cav0, cav1, ...)", lambda v: len(v) > 0)
    modality: Literal["lidar", "camera"] = "camera"
    encoder: Literal["pointpillars", "sinbevt", "lara"] = "sinbevt"


@dataclass(frozen=True)
class CavsConfig:
    count: int = _f(4, "1..16", lambda v: 1 <= v <= 16)
    ego: str | tuple[str, ...] = _f("first", "'first', 'all' or a list of CAV ids",
                                    lambda v: not isinstance(v, str) or v in ("first", "all"))
    arrival_s: tuple[float, float] = _f((0.0, 4.0), "[lo, hi] with 0 <= lo <= hi <= 60 (seconds after frame 0 "
                                        "at which the CAVs reach the junction at free-flow speed)",
                                        lambda v: 0 <= v[0] <= v[1] <= 60)
    meet: MeetConfig = field(default_factory=MeetConfig)
    # the movement of CAV i (cav0 first) through the junction in every placement candidate, where given: e.g.
    # [left] makes the ego turn left across oncoming traffic (empty: the placement's own choice)
    movements: tuple[Literal["straight", "left", "right"], ...] = ()
    # a mixed fleet: groups of CAVs with their own sensor and encoder; a CAV in no group runs perception.modality
    # and perception.encoder (empty: every CAV does, as in every single-modality run)
    fleet: tuple[FleetGroup, ...] = ()
    # the share of the placed vehicles besides the egos that are connected, drawn per seed (the others are ordinary
    # SUMO-driven vehicles; v2vsim/traffic/penetration.py); null: all of them
    penetration: float | None = _f(None, "0..1 or null (every placed vehicle connected)", _prob)

    def egos_among(self, present: typing.Sequence[str]) -> list[str]:
        """The CAVs that fuse (and, in a closed loop, drive), from `ego` (first | all | list of ids) and the CAVs
        present, in `present`'s order for first and all."""
        if self.ego == "first":
            return list(present[:1])
        if self.ego == "all":
            return list(present)
        return [c for c in self.ego if c in present]
