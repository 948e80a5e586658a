"""Trust that remembers (issue 67 item 3): a sender's reputation from the checks it passed and failed, frame after
frame, so that a lie caught once is not fused again at the next frame.

The beta reputation system (Jøsang and Ismail, "The Beta Reputation System", Bled eCommerce 2002, Eqs. 1-4, with
its forgetting factor): per sender, evidence for r and against s, each frame

    flagged:              r <- 0,                s <- forget * s + lie_weight
    judged, not flagged:  r <- forget * r + 1,   s <- forget * s
    not judged:           r <- forget * r,       s <- forget * s
    reputation = (r + 1) / (r + s + 2)           (the mean of Beta(r + 1, s + 1); 0.5 knowing nothing)

and the defence leaves out a sender whose reputation is below one half, i.e. while its evidence against outweighs
its evidence for. A flag wipes what its honest past had earned (an attacker that behaves until it matters buys
nothing with it), so a sender flagged once is out until it has passed k judged frames with
(1 - forget^k) / (1 - forget) > lie_weight * forget^k: 8 frames with the defaults (forget 0.95, lie_weight 10),
more the more often it was flagged; a sender out of everyone's view earns nothing back.
"""

from __future__ import annotations

from dataclasses import dataclass

TRUSTED = 0.5  # fused at or above this reputation


@dataclass(frozen=True)
class Standing:
    """One sender's evidence for (r) and against (s)."""

    r: float = 0.0
    s: float = 0.0

    @property
    def reputation(self) -> float:
        return (self.r + 1.0) / (self.r + self.s + 2.0)

    @property
    def trusted(self) -> bool:
        return self.r >= self.s  # reputation >= TRUSTED, without rounding


def update(st: Standing, judged: bool, flagged: bool, forget: float, lie_weight: float) -> Standing:
    """The standing after one frame (flagged implies judged)."""
    if flagged:
        return Standing(0.0, forget * st.s + lie_weight)
    return Standing(forget * st.r + (1.0 if judged else 0.0), forget * st.s)
