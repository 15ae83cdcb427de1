"""The stick band read off the stick-jump episodes, beside the Hammerstein estimate.

A sticky valve stops when OP turns; OP must then travel the whole band ``S``
(deadband plus stick band) the other way before the valve slips (Kano et al.
2004, the sticking section after a reversal; He et al. 2007: ``fs + fd``).
So the OP travel from OP's turning point to the slip measures ``S`` itself,
wherever the hold that PV shows begins: PV keeps answering the previous slip
for a while after the valve stopped, so the hold's own OP travel
(:func:`analytics.diagnosis.episode_stick_band`) misses the first part of the
band and reads low (0.38-0.81 S on the stiction cycles of the synthetic library,
median 0.67).
Without a reversal the valve, pushed on the same way after it stopped, slips
again after ``J`` in Kano's model: that travel lies between ``J`` and ``S``.

:func:`episode_size` measures, for every episode, OP's travel from the
extreme it reached since the previous slip (a turning point beyond OP's noise,
or a change of push direction between episodes: a reversal) to the slip, and
takes the median over the reversals as ``S``.  On the stiction cycles of the
synthetic library (24 windows with reversals, He and Kano valves, S 2-8 %) it
lies within 0.95-1.10 of the simulated ``S`` (median 1.02); on the stick-jump
windows of the non-oscillating library, mostly one or two reversals each, within
0.6-1.9 (median 0.95).  On the real loops of the ISDB and plant_dev that have
both, it agrees with the Hammerstein ``S`` within 5 % on CHEM10, CHEM23 and
FIC-05 (1.89 / 1.82, 27.6 / 27.3, 0.61 / 0.60 %).

:func:`compare_sizes` says whether the two independent estimates agree.

References
----------
.. [1] M. Kano, H. Maruta, H. Kugemoto and K. Shimizu, "Practical model and
   detection algorithm for valve stiction", IFAC DYCOPS, Cambridge MA, 2004.
.. [2] Q. P. He, J. Wang, M. Pottmann and S. J. Qin, "A curve fitting method for
   detecting valve stiction in oscillating control loops", Ind. Eng. Chem. Res.
   46 (2007) 4549-4560 (the two-parameter model: ``S = fs + fd``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from analytics.serial import Reader
from analytics.stiction.stick_jump import StickEpisode, moving_average, robust_noise
from analytics.types import FloatArray

__all__ = ["EPISODE_S_ERROR", "EpisodeSize", "SizeComparison", "compare_sizes", "episode_size"]

TURN_NOISE_SIGMAS = 3.0
"""OP must come back this many noise standard deviations from where it stood at
the previous slip for its extreme to count as a turning point."""

SMOOTHING = 3
"""Samples of the moving average through which OP is read (as the finest scale of
:func:`analytics.stiction.stick_jump.analyse_window`)."""

EPISODE_S_ERROR = 0.10
"""Relative error of the episodes' ``S`` on the stiction cycles of the synthetic
library (0.95-1.10 of the simulated S): how far beyond the Hammerstein interval it
may lie and still agree."""


@dataclass(frozen=True)
class EpisodeSize:
    """The valve's bands read off its stick-jump episodes (module docstring).

    Attributes
    ----------
    S : float or None
        Median OP travel from a turning point to the slip over the episodes after a
        reversal (OP units); None without a reversal.
    S_range : tuple of float or None
        The smallest and largest of those travels.
    reversals : int
        Episodes after a reversal.
    same_direction_band : float or None
        Median OP travel between slips without a reversal: between ``J`` and ``S``
        (Kano's valve slips again after ``J``); None without such episodes.
    same_direction : int
        Episodes without a reversal.
    """

    S: float | None
    S_range: tuple[float, float] | None
    reversals: int
    same_direction_band: float | None
    same_direction: int

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready form."""
        return {"S": self.S, "S_range": None if self.S_range is None else list(self.S_range),
                "reversals": self.reversals, "same_direction_band": self.same_direction_band,
                "same_direction": self.same_direction}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str = "episode size") -> EpisodeSize:
        """The size of :meth:`to_dict`'s form (``to_dict(from_dict(d)) == d``); a missing
        field raises :class:`~analytics.errors.DataError` naming it and ``where``."""
        read = Reader(d, where)
        return cls(read("S"), None if read("S_range") is None else read.pair("S_range"),
                   read("reversals"), read("same_direction_band"), read("same_direction"))


@dataclass(frozen=True)
class SizeComparison:
    """The episodes' ``S`` against the Hammerstein estimate's.

    Attributes
    ----------
    agree : bool
        True when the episodes' ``S`` lies within the Hammerstein interval, widened
        by :data:`EPISODE_S_ERROR`.
    note : str
        One sentence for the ticket: both values and what a disagreement means.
    """

    agree: bool
    note: str


def episode_size(op: FloatArray, episodes: Sequence[StickEpisode]) -> EpisodeSize | None:
    """:class:`EpisodeSize` of ``episodes`` found in ``op``; None without episodes.

    Each episode's travel runs from the extreme of the smoothed OP since the
    previous slip (the episode's hold start for the first) to its own slip.  It
    follows a reversal when that extreme lies beyond :data:`TURN_NOISE_SIGMAS`
    noise standard deviations back from where OP stood at the previous slip, or
    when OP pushes the other way than in the episode before.
    """
    if not episodes:
        return None
    smooth = moving_average(np.asarray(op, dtype=np.float64), SMOOTHING)
    threshold = TURN_NOISE_SIGMAS * robust_noise(np.asarray(op, dtype=np.float64))
    after_reversal: list[float] = []
    same_direction: list[float] = []
    previous: StickEpisode | None = None
    for episode in episodes:
        since = previous.jump_at if previous is not None else episode.start
        stretch = smooth[since : episode.jump_at + 1]
        push = 1.0 if episode.op_travel > 0 else -1.0
        turn = float(stretch.min() if push > 0 else stretch.max())
        travel = abs(float(smooth[episode.jump_at]) - turn)
        turned = abs(turn - float(smooth[since])) > threshold
        pushed_back = previous is not None and (previous.op_travel > 0) != (push > 0)
        (after_reversal if turned or pushed_back else same_direction).append(travel)
        previous = episode
    return EpisodeSize(
        S=float(np.median(after_reversal)) if after_reversal else None,
        S_range=(min(after_reversal), max(after_reversal)) if after_reversal else None,
        reversals=len(after_reversal),
        same_direction_band=float(np.median(same_direction)) if same_direction else None,
        same_direction=len(same_direction),
    )


def compare_sizes(episodes: EpisodeSize, S: float,
                  S_interval: tuple[float, float] | None) -> SizeComparison | None:
    """Whether the episodes' ``S`` agrees with a Hammerstein ``S`` (and its interval);
    None when the episodes show no reversal."""
    if episodes.S is None:
        return None
    low, high = S_interval if S_interval is not None else (S, S)
    interval = "" if S_interval is None else f", 95 % interval {low:.2f}-{high:.2f}"
    low, high = low * (1.0 - EPISODE_S_ERROR), high * (1.0 + EPISODE_S_ERROR)
    counted = (f"{episodes.reversals} episode{'s' if episodes.reversals != 1 else ''} after "
               "an OP reversal")
    if low <= episodes.S <= high:
        return SizeComparison(True, f"the episodes agree: OP travelled {episodes.S:.2f} from "
                                    f"its turn to the slip ({counted}), the Hammerstein model "
                                    f"gives S = {S:.2f}{interval}")
    why = ("the valve held through more OP travel than the fitted model lets it: the "
           "Hammerstein S is too small, or the valve's band changed in the window"
           if high < episodes.S else
           "the valve slipped after less OP travel than the fitted model needs: the "
           "Hammerstein S is too large, or some slips are not the valve's")
    return SizeComparison(False, f"the episodes disagree: OP travelled {episodes.S:.2f} from "
                                 f"its turn to the slip ({counted}) against the Hammerstein "
                                 f"S = {S:.2f}{interval}; {why}")
