"""What the ego hands over to be reported (`RunSummary`): the run's scenario, its ego and methods, and what the ego
counted and chose beside the scores (frames, timing, lost agents, checkpoints, compensation, the closed loop's
driving block, ...). metrics_doc and report_md read it; report.write_outputs writes them."""

from __future__ import annotations

from dataclasses import dataclass, field

from v2vsim.config import Scenario


@dataclass
class RunSummary:
    scenario: Scenario
    ego: str
    methods: list[str]
    untrained: bool
    frames: int = 0
    status: str = "complete"
    wall_s: float = 0.0
    sim_s: float = 0.0  # simulated seconds covered (realtime runs may skip frames)
    lost_agents: dict[str, int] = field(default_factory=dict)  # CAV id -> frame it was lost at
    skipped: list[str] = field(default_factory=list)  # methods the modality cannot run
    neighbours: list[int] = field(default_factory=list)  # per fused frame: other CAVs within comm.range_m
    checkpoints: dict[str, str | None] = field(default_factory=dict)  # method -> zoo file (None: random init)
    timing: dict = field(default_factory=dict)  # the ego's StageTimer.to_json(): ms per frame by stage
    compensation: dict[str, str] = field(default_factory=dict)  # method -> how its late messages are compensated
    grid_cells: int = 0  # the fusion grid F of the feature messages (F x F cells over bev.size_m)
    channels: int = 0  # C of the encoder's feature map
    wire_ratio: int = 1  # channel compression of the feature messages: C / r channels on the wire
    driving: dict | None = None  # closed loop: metrics.json `driving` (v2vsim.control.measures.driving_block)
    # where the ego's models ran: metrics.json `device` (v2vsim.perception.device.device_record); None: not said
    device: dict[str, str] | None = None
    # a mixed fleet (cavs.fleet): CAV id -> its agent type's label (v2vsim.perception.fleet); empty otherwise
    fleet: dict[str, str] = field(default_factory=dict)
    feature_bytes: dict[str, int] = field(default_factory=dict)  # feature-message bytes received, by sender
    defence: dict | None = None  # defence.detect/exclude: metrics.json `defence` (agents.ego_defence.SenderCheck)
