"""The work one analysis worker does for one loop window.

:func:`analyse_window` runs in a worker process (local pool or Dask), so it
takes and returns plain data: the loop's configuration as a dict and the
window's arrays; it returns the JSON-ready diagnosis with a health score.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from analytics.diagnosis import diagnose_loop

__all__ = ["analyse_window", "health_score", "to_percent_of_span"]

FloatArray = NDArray[np.float64]


def to_percent_of_span(x: FloatArray | None, span: tuple[float, float] | None) -> FloatArray | None:
    """``100 (x - low) / (high - low)``; unchanged when no range is configured."""
    if x is None or span is None:
        return x
    low, high = span
    return np.asarray(100.0 * (x - low) / (high - low), dtype=np.float64)


def health_score(diagnosis: dict[str, Any]) -> float | None:
    """Loop health from 0 (bad actor) to 100 (healthy); None when data are unusable.

    A loop that does not oscillate scores 100 less 5 per data-quality warning
    (at most 20).  An oscillating loop starts at 70 and loses up to 30 for a
    regular oscillation (regularity r, ``min(r, 10) / 10 * 30``, Thornhill et
    al. 2003: the more regular, the more certainly a persistent cycle) and up
    to 40 for a stiction verdict (confidence * 40): a regularly cycling loop
    with a confidently sticky valve is the worst actor.
    """
    if not diagnosis["quality"]["usable"]:
        return None
    warnings = sum(1 for i in diagnosis["quality"]["issues"] if i["severity"] == "warning")
    osc = diagnosis["oscillation"]
    if not osc["detected"]:
        return float(100 - min(20, 5 * warnings))
    score = 70.0 - min(float(osc["regularity"] or 0.0), 10.0) / 10.0 * 30.0
    stiction = diagnosis["stiction"]
    if stiction["verdict"] == "stiction":
        score -= 40.0 * float(stiction["confidence"])
    return max(0.0, score)


def analyse_window(
    loop: dict[str, Any],
    ts: float,
    t: FloatArray,
    signals: dict[str, FloatArray | None],
) -> dict[str, Any]:
    """Diagnose one window of one loop; signals are converted to % of span first.

    Parameters
    ----------
    loop : dict
        The loop's configuration (``LoopConfig.model_dump()``).
    ts, t : float, ndarray
        Sampling interval and sample times (s).
    signals : dict
        ``op``, ``pv``, ``sp``, ``mv`` arrays (NaN where missing) or None.
    """
    ranges: dict[str, tuple[float, float]] = {
        k: (float(v[0]), float(v[1])) for k, v in (loop.get("ranges") or {}).items()
    }
    if "pv" in ranges:
        ranges.setdefault("sp", ranges["pv"])  # the set point is in PV units
    scaled = {name: to_percent_of_span(x, ranges.get(name)) for name, x in signals.items()}
    diagnosis = diagnose_loop(
        ts=ts, t=t, op=scaled.get("op"), pv=scaled.get("pv"), sp=scaled.get("sp"),
        mv=scaled.get("mv"), process_type=loop.get("process_type"),
        ranges={name: (0.0, 100.0) for name in ranges},
    ).to_dict()
    diagnosis["health"] = health_score(diagnosis)
    return diagnosis
