"""The KPI-based bad-actor score: KPI severity x loop importance x time spent bad.

Each stored analysis run carries the KPIs of its window (its result's ``kpis``,
:func:`service.analysis.analyse_window`, also in its ``kpis`` column).  Over a period
the score of a loop is

``score = 100 x severity x weight(importance) x bad_share``

* a run's **severity** (0..1) is its worst KPI component
  (:data:`COMPONENTS`): the oscillation index, the Desborough-Harris
  normalised index beyond 0.5 (``(eta - 0.5) / 0.5``: more than twice the
  minimum variance), the share of time OP saturated, the share of time PV
  spent outside its configured limits, the share of time not in normal mode,
  and the diagnosis's ``1 - health / 100`` (stiction, data quality);
* a run is **bad** when its severity is at least :data:`BAD_SEVERITY`;
  ``bad_share`` is the share of the period's analysed runs that were bad
  (time spent bad, not only the latest run);
* ``severity`` of the loop is the mean severity of its bad runs;
* the importance **weight** is :data:`IMPORTANCE_WEIGHT` (low 0.5, medium 1,
  high 1.5, critical 2).

A loop bad in every run of the week with a strong regular oscillation
(severity 0.8) and importance high scores 120; a loop never bad scores 0.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from pydantic import BaseModel, ConfigDict

from service.stored import StoredKpis

__all__ = [
    "BAD_SEVERITY",
    "COMPONENTS",
    "IMPORTANCE_WEIGHT",
    "SCORED_KPIS",
    "LoopScore",
    "run_components",
    "run_severity",
    "score_loop",
    "scored_kpis",
]

BAD_SEVERITY = 0.3
"""A run whose worst KPI component reaches this is a bad run."""

IMPORTANCE_WEIGHT: dict[str, float] = {"low": 0.5, "medium": 1.0, "high": 1.5, "critical": 2.0}

COMPONENTS: dict[str, str] = {
    "oscillation": "oscillation index",
    "variance": "variance above minimum (Harris)",
    "saturation": "OP at its limits",
    "limits": "PV outside its limits",
    "manual": "not in normal mode",
    "diagnosis": "diagnosis (health)",
}
"""The severity components of a run and how the ``why`` names them."""


SCORED_KPIS: tuple[tuple[str, ...], ...] = (
    ("oscillation_index",), ("harris", "normalised"), ("saturation",),
    ("error", "within_limits"), ("service_factor", "normal"),
)
"""The paths in a run's KPIs (:meth:`analytics.kpi.LoopKpis.to_dict`) that
:func:`run_components` reads: a store can extract them without the rest."""


def scored_kpis(values: Sequence[float | None]) -> StoredKpis:
    """The KPIs of a run rebuilt from the values at :data:`SCORED_KPIS` (None where a
    run has none): :func:`run_components` gives the same components as from the whole.

    >>> kpis = {"oscillation_index": 0.5, "saturation": 0.1, "harris": {"normalised": 0.75},
    ...         "error": {"within_limits": None, "std": 2.0}, "service_factor": None}
    >>> scored_kpis([0.5, 0.75, 0.1, None, None]).harris_normalised
    0.75
    >>> run_components(40.0, scored_kpis([0.5, 0.75, 0.1, None, None])) == run_components(
    ...     40.0, StoredKpis.from_dict(kpis))
    True
    """
    oscillation, normalised, saturation, within, normal = values
    return StoredKpis(oscillation_index=oscillation, harris_normalised=normalised,
                      saturation=saturation, within_limits=within, service_factor=normal)


def run_components(health: float | None, kpis: StoredKpis | None) -> dict[str, float]:
    """The severity components (0..1) of one run: those its KPIs and health measure.

    >>> run_components(40.0, StoredKpis.from_dict({"oscillation_index": 0.5, "saturation": 0.1,
    ...     "harris": {"normalised": 0.75}, "error": {"within_limits": None},
    ...     "service_factor": None}))
    {'oscillation': 0.5, 'variance': 0.5, 'saturation': 0.1, 'diagnosis': 0.6}
    """
    out: dict[str, float] = {}
    k = kpis or StoredKpis()
    if k.oscillation_index is not None:
        out["oscillation"] = float(k.oscillation_index)
    if k.harris_normalised is not None:
        out["variance"] = min(1.0, max(0.0, (float(k.harris_normalised) - 0.5) / 0.5))
    if k.saturation is not None:
        out["saturation"] = float(k.saturation)
    if k.within_limits is not None:
        out["limits"] = 1.0 - float(k.within_limits)
    if k.service_factor is not None:
        out["manual"] = 1.0 - float(k.service_factor)
    if health is not None:
        out["diagnosis"] = 1.0 - float(health) / 100.0
    return out


def run_severity(health: float | None, kpis: StoredKpis | None) -> float:
    """A run's severity: its worst component (:func:`run_components`), 0 without any.

    >>> run_severity(90.0, StoredKpis(oscillation_index=0.4)), run_severity(None, None)
    (0.4, 0.0)
    """
    return max(run_components(health, kpis).values(), default=0.0)


class LoopScore(BaseModel):
    """A loop's bad-actor score over a period and why: the fields the bad-actor ranking
    adds to each loop (:class:`service.api.schemas.loops.BadActorPublic`).

    Attributes
    ----------
    score : float
        ``100 x severity x weight x bad_share``.
    severity : float
        Mean severity of the bad runs (0 without any).
    bad_share : float
        Share of the period's analysed runs that were bad.
    runs, bad_runs : int
        Analysed runs in the period, and how many were bad.
    worst : str or None
        The component that was worst on average over the bad runs.
    why : str
        The score in words.
    """

    score: float
    severity: float
    bad_share: float
    runs: int
    bad_runs: int
    worst: str | None
    why: str

    model_config = ConfigDict(frozen=True)


def score_loop(runs: Iterable[tuple[float | None, StoredKpis | None]], importance: str,
               period: str) -> LoopScore:
    """The bad-actor score of one loop from its runs ``(health, kpis)`` over ``period``.

    >>> s = score_loop([(100.0, StoredKpis(oscillation_index=0.8))] * 3
    ...                + [(100.0, StoredKpis(oscillation_index=0.0))], "high", "7d")
    >>> s.score, s.bad_runs, s.worst
    (90.0, 3, 'oscillation')
    >>> s.why
    'bad in 3 of 4 runs (75 %) over 7d; worst: oscillation index 0.80; importance high (x1.5)'
    """
    weight = IMPORTANCE_WEIGHT.get(importance, 1.0)
    severities: list[float] = []
    totals: dict[str, float] = {}
    n = 0
    for health, kpis in runs:
        n += 1
        components = run_components(health, kpis)
        severity = max(components.values(), default=0.0)
        if severity >= BAD_SEVERITY:
            severities.append(severity)
            for name, value in components.items():
                totals[name] = totals.get(name, 0.0) + value
    if n == 0:
        return LoopScore(score=0.0, severity=0.0, bad_share=0.0, runs=0, bad_runs=0, worst=None,
                         why=f"no analysed run over {period}")
    bad = len(severities)
    if bad == 0:
        return LoopScore(score=0.0, severity=0.0, bad_share=0.0, runs=n, bad_runs=0, worst=None,
                         why=f"bad in none of {n} runs over {period}")
    severity = sum(severities) / bad
    share = bad / n
    worst = max(totals, key=lambda name: totals[name])
    why = (f"bad in {bad} of {n} runs ({100 * share:.0f} %) over {period}; worst: "
           f"{COMPONENTS[worst]} {totals[worst] / bad:.2f}; "
           f"importance {importance} (x{weight:g})")
    return LoopScore(score=round(100.0 * severity * weight * share, 6), severity=severity,
                     bad_share=share, runs=n, bad_runs=bad, worst=worst, why=why)
