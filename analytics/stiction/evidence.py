"""The contract every stiction detector follows.

A detector is a frozen dataclass: its fields are its settings (keyword-only,
with the published defaults), it learns nothing, and
``detect(window) -> MethodEvidence`` is a pure function of the window.  A
method that cannot apply to a window (a signal missing, no oscillation, a
process type it does not cover) says so with an ``undecided`` evidence and
the reason, never a guess.  ``tests/analytics/stiction/test_contract.py``
runs the same checks over every registered detector.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import ClassVar, Literal, Protocol

import numpy as np

from analytics.errors import DataError
from analytics.types import INTEGRATING, SELF_REGULATING, FloatArray, ProcessType

__all__ = [
    "INTEGRATING",
    "NO_STICTION",
    "SELF_REGULATING",
    "STICTION",
    "UNDECIDED",
    "Decision",
    "Detector",
    "LoopWindow",
    "MethodEvidence",
    "ProcessType",
    "margin_confidence",
]


Decision = Literal["stiction", "no_stiction", "undecided"]
STICTION: Decision = "stiction"
NO_STICTION: Decision = "no_stiction"
UNDECIDED: Decision = "undecided"


def _as_signal(x: object, name: str) -> FloatArray | None:
    if x is None:
        return None
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 1:
        raise DataError(f"{name} must be one-dimensional, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        bad = int(np.flatnonzero(~np.isfinite(a))[0])
        raise DataError(f"{name} has a non-finite value at index {bad}")
    return a


@dataclass(frozen=True)
class LoopWindow:
    """One window of a control loop, as the detectors see it.

    Attributes
    ----------
    ts : float
        Sampling interval in seconds.
    op, pv, sp, mv : ndarray or None
        Controller output, process variable, set point and measured valve
        position, equally long, finite; any may be None (at least one of OP
        and PV is given).  Units are the plant's own; OP is preferably in %
        of span.
    process_type : {"self-regulating", "integrating"} or None
        Process type if known (given by the user or inferred by the
        pipeline); None when unknown.
    period_s : float or None
        Period of the loop oscillation if one was detected
        (:func:`analytics.oscillation.detect_loop_oscillation`); None if the
        loop does not oscillate.
    """

    ts: float
    op: FloatArray | None
    pv: FloatArray | None
    sp: FloatArray | None = None
    mv: FloatArray | None = None
    process_type: ProcessType | None = None
    period_s: float | None = None

    def __post_init__(self) -> None:
        if not (np.isfinite(self.ts) and self.ts > 0):
            raise DataError(f"ts must be a positive number of seconds, got {self.ts!r}")
        sizes = {}
        for name in ("op", "pv", "sp", "mv"):
            a = _as_signal(getattr(self, name), name)
            object.__setattr__(self, name, a)
            if a is not None:
                sizes[name] = a.size
        if self.op is None and self.pv is None:
            raise DataError("a loop window needs at least one of op and pv")
        if len(set(sizes.values())) > 1:
            raise DataError(f"signals differ in length: {sizes}")
        if self.process_type not in (None, SELF_REGULATING, INTEGRATING):
            raise DataError(
                f"process_type must be 'self-regulating', 'integrating' or None, "
                f"got {self.process_type!r}"
            )
        if self.period_s is not None and not (np.isfinite(self.period_s) and self.period_s > 0):
            raise DataError(f"period_s must be positive or None, got {self.period_s!r}")

    @property
    def samples(self) -> int:
        """Number of samples in the window."""
        ref = self.op if self.op is not None else self.pv
        assert ref is not None
        return int(ref.size)

    @property
    def period_samples(self) -> float | None:
        """Oscillation period in samples, or None."""
        return None if self.period_s is None else self.period_s / self.ts


@dataclass(frozen=True)
class MethodEvidence:
    """What one detection method found in one window.

    Attributes
    ----------
    method : str
        The detector's registry name (e.g. ``"cross_correlation"``).
    decision : {"stiction", "no_stiction", "undecided"}
        The method's own decision with its published thresholds.
    index : float or None
        The method's index (e.g. the area ratio, NGI); None if it could not
        be computed.
    confidence : float
        0 to 1: how clearly the index lies on its side of the thresholds
        (0 for undecided, or exactly at a threshold).
    note : str
        One sentence for a human: what the index means here, or why the
        method is undecided.
    details : mapping of str to float
        Further numbers worth showing (secondary indices, fit errors).
    """

    method: str
    decision: Decision
    index: float | None
    confidence: float
    note: str
    details: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.decision not in (STICTION, NO_STICTION, UNDECIDED):
            raise ValueError(f"unknown decision {self.decision!r}")
        if not 0.0 <= self.confidence <= 1.0:
            raise ValueError(f"confidence must lie in [0, 1], got {self.confidence!r}")
        if self.decision == UNDECIDED and self.confidence != 0.0:
            raise ValueError("an undecided evidence has confidence 0")

    @classmethod
    def undecided(
        cls, method: str, note: str, index: float | None = None,
        details: Mapping[str, float] | None = None,
    ) -> MethodEvidence:
        """An undecided evidence with the reason in ``note``."""
        return cls(method, UNDECIDED, index, 0.0, note, dict(details or {}))


def margin_confidence(index: float, threshold: float, scale: float) -> float:
    """Confidence from how far ``index`` lies from ``threshold``.

    ``1 - exp(-|index - threshold| / scale)``: 0 at the threshold, about 0.63
    one ``scale`` away, approaching 1 far away.

    Examples
    --------
    >>> margin_confidence(0.5, 0.5, 0.1)
    0.0
    >>> round(margin_confidence(0.7, 0.5, 0.1), 3)
    0.865
    """
    if scale <= 0:
        raise ValueError(f"scale must be positive, got {scale!r}")
    return float(1.0 - np.exp(-abs(index - threshold) / scale))


class Detector(Protocol):
    """A stiction detection method (see the module docstring)."""

    name: ClassVar[str]

    def detect(self, window: LoopWindow) -> MethodEvidence:
        """Evidence for or against stiction in ``window``."""
        ...
