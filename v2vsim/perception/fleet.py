"""A run's fleet: which sensor and encoder each CAV carries (cavs.fleet; docs/scenario.md "A mixed fleet").

A CAV in no group of cavs.fleet is of the base type, perception.modality / perception.encoder; in a mixed fleet
the others carry an encoder backward-aligned into the base's feature space (models.aligner, the `align` stage),
so every intermediate method of the base zoo fuses their messages as they are."""

from __future__ import annotations

from dataclasses import dataclass

from v2vsim.config import Scenario

MODALITY_NAMES = {"lidar": "LiDAR", "camera": "camera"}


@dataclass(frozen=True)
class AgentType:
    """One kind of CAV: its sensor and the encoder that turns it into BEV features."""

    modality: str  # "lidar" | "camera"
    encoder: str  # models.registry.ENCODERS

    @property
    def label(self) -> str:
        """How reports name it, e.g. "camera (sinbevt)"."""
        return f"{MODALITY_NAMES[self.modality]} ({self.encoder})"


def base_type(sc: Scenario) -> AgentType:
    """The type of every CAV that no fleet group names: the scenario's perception section."""
    return AgentType(sc.perception.modality, sc.perception.encoder)


def is_mixed(sc: Scenario) -> bool:
    """Whether the scenario gives some CAVs their own sensor and encoder (cavs.fleet is not empty)."""
    return bool(sc.cavs.fleet)


def agent_type(sc: Scenario, cav: str) -> AgentType:
    """The sensor and encoder of CAV `cav`."""
    for group in sc.cavs.fleet:
        if cav in group.cavs:
            return AgentType(group.modality, group.encoder)
    return base_type(sc)


def fleet_types(sc: Scenario, cavs: list[str] | tuple[str, ...]) -> dict[str, AgentType]:
    """Each of `cavs` -> its AgentType."""
    return {c: agent_type(sc, c) for c in cavs}


def extra_types(sc: Scenario) -> list[AgentType]:
    """The types of the fleet groups other than the base's, once each, in the order the groups name them."""
    out: list[AgentType] = []
    for group in sc.cavs.fleet:
        t = AgentType(group.modality, group.encoder)
        if t != base_type(sc) and t not in out:
            out.append(t)
    return out
