"""The scenario schema (DESIGN.md "Scenario YAML"): `Scenario`, the frozen dataclass of a whole scenario YAML, with
its top-level fields and the `output` section. Each other section is a frozen dataclass of its own module, whose
field metadata says what is allowed: schema_traffic (traffic, cavs), schema_perception (sensors, bev, perception,
evaluation), schema_comm (comm, transport), schema_control (control), schema_misbehaviour (misbehaviour,
defence); their field helper is schema_fields."""

from __future__ import annotations

from dataclasses import dataclass, field

from v2vsim.config.schema_comm import CommConfig, TransportConfig
from v2vsim.config.schema_control import ControlConfig
from v2vsim.config.schema_fields import _f, _pos
from v2vsim.config.schema_misbehaviour import DefenceConfig, Lie
from v2vsim.config.schema_perception import BevConfig, EvaluationConfig, PerceptionConfig, SensorsConfig
from v2vsim.config.schema_traffic import CavsConfig, TrafficConfig

SEED_MAX = 2**31 - 1  # SUMO (libsumo --seed) takes a signed 32-bit seed


@dataclass(frozen=True)
class OutputConfig:
    dir: str = "runs/intersection"
    rerun: bool = True
    # true: the ego also keeps what it received, frame by frame (messages/ beside metrics.json, docs/run.md
    # "Record once, evaluate many"), for `v2vsim evaluate` to replay with other receiver-side keys; lockstep only
    record_messages: bool = False


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
    control: ControlConfig | None = None  # closed loop when present (docs/scenario.md "control")
    misbehaviour: tuple[Lie, ...] = ()  # CAVs that lie on purpose (an attacked run; docs/scenario.md "misbehaviour")
    defence: DefenceConfig = field(default_factory=DefenceConfig)  # the ego's misbehaviour check (docs: "defence")
    source: str = field(default="<defaults>", metadata={"internal": True})  # the YAML file
    overrides: tuple[str, ...] = field(default=(), metadata={"internal": True})  # --set, for child processes

    @property
    def frames(self) -> int:
        return max(1, round(self.duration_s * self.rate_hz))

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def actuation_delay_frames(self) -> int:
        """Frames between the capture a plan rests on and the step it is applied after (closed loop)."""
        d = None if self.control is None else self.control.actuation_delay_frames
        return self.transport.pipeline if d is None else d

    @property
    def fusion_deadline_s(self) -> float:
        """How long after a frame's capture the ego fuses it: comm.fusion_deadline_ms, or half a frame."""
        ms = self.comm.fusion_deadline_ms
        return 0.5 * self.dt if ms is None else ms / 1000.0
