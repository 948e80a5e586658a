"""The contract every traffic backend implements, and the small pieces they share.

Why a Protocol: the runner, the PettingZoo env and the tests only need `static`, `reset`,
`step` and `close`; SUMO and highway-env differ in everything else. `BackendBase` gives the
context-manager behaviour once, so `with make_backend(sc) as tb:` always closes the
simulator (libsumo can only run one simulation per process, so a leaked one blocks the next).

Conventions (all backends):
- CAV ids are "cav0".."cav{N-1}" (`Actor.cav=True`), numbered in insertion order; "cav0" is
  the default ego.
- `WorldState.time` is seconds since frame 0 (frame * 1/rate_hz); frame 0 is what `reset()`
  returns, after the backend's warm-up.
- A vehicle that leaves the simulation is simply absent from later `actors`; a CAV that leaves
  never comes back (its agent ends).
- Actors are ordered CAVs first (cav0, cav1, ...), then background vehicles in the order they
  entered, so two runs with the same seed give identical tuples.
"""

from __future__ import annotations

from types import TracebackType
from typing import Protocol, Self, runtime_checkable

from v2vsim.world.state import StaticMap, WorldState


def cav_id(index: int) -> str:
    """The id of the index-th CAV (0-based)."""
    return f"cav{index}"


@runtime_checkable
class TrafficBackend(Protocol):
    """A traffic simulator seen as a sequence of WorldStates."""

    @property
    def static(self) -> StaticMap:
        """The static map (roads, markings, buildings); available before `reset()`."""
        ...

    def reset(self) -> WorldState:
        """(Re)start the simulation; return frame 0, after `traffic.warmup_s` of background traffic."""
        ...

    def step(self) -> WorldState:
        """Advance by 1/rate_hz and return the next frame."""
        ...

    def close(self) -> None:
        """Release the simulator; idempotent. Another backend may start afterwards."""
        ...

    def __enter__(self) -> Self: ...

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None: ...


class BackendBase:
    """Context-manager plumbing shared by the concrete backends (subclasses define close())."""

    def close(self) -> None:  # pragma: no cover - always overridden
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def __del__(self) -> None:
        # Best effort only: an explicit close() (or `with`) is the supported way.
        try:
            self.close()
        except Exception:  # interpreter shutdown may have torn modules down already
            pass
