"""Plots of a loop as SVG or PNG: ``GET /api/v1/loops/{id}/plots/{kind}``.

The route gathers the data (samples from the store or the rolling buffer,
the latest diagnosis, the loop's configuration) and hands them to the figure
builders of :mod:`service.plots`.  Kinds:

* ``trend``: SP, PV, OP, MV between ``start`` and ``end`` (default: the last
  hour), from the same query as ``GET /loops/{id}/data``.
* ``signature``, ``spectrum``: the window of the latest analysis, in % of
  span as the analysis saw it, with the period it used; the signature shows
  the OP-PV ellipse the analysis fitted (stored with a stiction verdict; fitted
  here for other verdicts, older analyses and the OP-MV signature: the analysis
  never sees MV) and the fitted stiction model's trace the analysis stored
  (:class:`analytics.replay.ModelTrace`; replayed here for analyses stored
  before it was kept).  The spectrum and ACF are computed here from the window
  (:mod:`analytics.signals`, the helpers the analysis uses), not stored: they
  are half a window of numbers per signal (about 60 kB of JSON per run of an
  hour at 1 s), and a coarser spectrum would not draw the same plot.
* ``nyquist``: ``G Gc`` and ``-1/N(A)`` for the process model identified by
  the latest stiction estimate, the configured controller and Choudhury's
  describing function at the estimated (S, J) (thesis Eq. 3.16).
* ``history``: health, S and J of the past analyses.

``POST /api/v1/loops/{id}/plots/model-check`` draws the overlay of a model
check (``POST /loops/{id}/model-check``, which takes seconds to run): the
caller sends back the ``overlay`` and ``cause`` of its answer and gets the
plot, so the check is not run a second time for its picture.

The window comes from the rolling buffer, or from the store when the buffer
does not hold it (an API replica of the scale-out topology has no buffers
of its own).  A plot that cannot be drawn yet (no analysis, no estimate,
samples purged from the store) answers 404 with the reason, which the
dashboard shows.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, HTTPException, Query, Response
from numpy.typing import NDArray
from pydantic import BaseModel
from sqlalchemy import select

from analytics.errors import DataError, ModelSpecError
from analytics.limit_cycle import nyquist_curves, predict_limit_cycles
from analytics.replay import ModelTrace, model_trace
from analytics.stiction.signature import EllipseFit, fit_signature_ellipse
from service import plots
from service.analysis import to_percent_of_span
from service.api.deps import (
    ERROR_RESPONSES,
    Reader,
    SessionDep,
    StateDep,
    TimeQuery,
)
from service.api.loop_data import read_loop_data
from service.api.schemas.files import BINARY, TEXT
from service.buffer import LoopBuffers, LoopWindowData
from service.config import LoopConfig
from service.loop_model import ModelUnavailableError, identified_loop
from service.store.models import AnalysisRun, Loop
from service.stored import StoredDiagnosis
from service.tickets import latest_loop_run

router = APIRouter(prefix="/api/v1/loops", tags=["plots"], responses=ERROR_RESPONSES)

PlotKind = Literal["trend", "signature", "spectrum", "nyquist", "history"]
PlotFormat = Literal["svg", "png"]
MEDIA_TYPES: dict[str, str] = {"svg": "image/svg+xml", "png": "image/png"}
IMAGE_CONTENT = {MEDIA_TYPES["svg"]: TEXT, MEDIA_TYPES["png"]: BINARY}
"""The OpenAPI content of a plot: SVG text or PNG bytes."""
HISTORY_RUNS = 200
"""Analyses shown by the ``history`` plot (the newest)."""
TREND_POINTS = 2000
"""Points per signal of the ``trend`` plot (min/max downsampling keeps cycles)."""


def _loop_or_404(session: SessionDep, loop_id: str) -> Loop:
    loop = session.get(Loop, loop_id)
    if loop is None:
        raise HTTPException(404, "Loop not found")
    return loop


def _latest_run(session: SessionDep, loop_id: str) -> AnalysisRun:
    run = latest_loop_run(session, loop_id)
    if run is None or run.result is None:
        raise HTTPException(404, f"No analysis of loop {loop_id} yet")
    return run


def _holds_samples(window: LoopWindowData) -> bool:
    return any(x is not None and np.isfinite(x).any() for x in (window.op, window.pv))


def _analysed_window(session: SessionDep, state: StateDep, loop: Loop, run: AnalysisRun
                     ) -> LoopWindowData:
    """The samples ``run`` diagnosed, in % of span: from the rolling buffer, else the store.

    With a stretch in manual that is the window's longest stretch in auto or
    cascade (the diagnosis's ``manual``, :func:`service.analysis.manual_stretch`).
    """
    assert run.window_start is not None and run.window_end is not None
    try:
        window = state.buffers.window(loop.id, run.window_end - run.window_start,
                                      run.window_end)
    except (KeyError, ValueError):
        window = None
    if window is None or not _holds_samples(window):  # not in this process's buffers
        stored = LoopBuffers.from_store(session, [LoopConfig.model_validate(loop.config)],
                                        since=run.window_start,
                                        now=max(state.clock(), run.window_end))
        window = stored.window(loop.id, run.window_end - run.window_start, run.window_end)
    if not _holds_samples(window):
        raise HTTPException(404, "Samples of the analysed window are no longer stored")
    manual = StoredDiagnosis.from_dict(run.result).manual
    judged: slice | NDArray[np.bool_] = slice(None)
    if manual is not None:
        if manual.judged_from is None or manual.judged_to is None:
            raise HTTPException(404, "The loop was in manual over the whole analysed window")
        judged = (window.t >= manual.judged_from) & (window.t <= manual.judged_to)
    ranges = loop.config.get("ranges") or {}
    scaled = {name: to_percent_of_span(x[judged], tuple(ranges[name]) if name in ranges else None)
              for name, x in window.signals.items()}
    return LoopWindowData(t=window.t[judged], op=scaled.get("op"), pv=scaled.get("pv"),
                          sp=scaled.get("sp"), mv=scaled.get("mv"), ts=window.ts)


def _ellipse(op: np.ndarray | None, valve: np.ndarray | None, period_samples: float | None
             ) -> EllipseFit | None:
    """The signature ellipse fitted here, or None without a period, with gaps or too few
    cycles: for the OP-MV signature, and for OP-PV when the analysis stored none."""
    if op is None or valve is None or period_samples is None:
        return None
    if not (np.isfinite(op).all() and np.isfinite(valve).all()):
        return None
    try:
        return fit_signature_ellipse(op, valve, period_samples)
    except DataError:
        return None


def _name(loop: Loop) -> str:
    return f"{loop.id} {loop.name}".strip()


def _title(loop: Loop, what: str, start: float, end: float) -> str:
    return f"{_name(loop)}: {what}, {(end - start) / 60:.0f} min to {plots.format_utc(end)}"


def _values(values: list[float | None]) -> np.ndarray:
    """JSON numbers with nulls as an array with NaN."""
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def _trend(session: SessionDep, state: StateDep, loop: Loop,
           start: float | None, end: float | None) -> plots.Figure:
    data = read_loop_data(session, loop.id, state.clock(), start, end, TREND_POINTS)
    series = {  # the mode tag is a state, not a trace (the loop page lists it)
        s.signal: (np.asarray(s.t, dtype=float), _values(s.value))
        for s in data.series if s.signal in plots.SIGNAL_LABELS
    }
    if not any(t.size for t, _ in series.values()):
        raise HTTPException(404, f"No samples of loop {loop.id} between {data.start:.0f} and "
                                 f"{data.end:.0f}")
    return plots.trend_figure(
        series, title=_title(loop, "trend", data.start, data.end),
        unit="plant units",
    )


def _fitted_model(op: np.ndarray, pv: np.ndarray, ts: float, diagnosis: StoredDiagnosis
                  ) -> ModelTrace | None:
    """The stiction estimate's valve and process replayed on the window, as the analysis
    stored it; replayed here for a run stored before the trace was kept
    (:func:`analytics.replay.model_trace`).  None without an estimate."""
    stored, estimate = diagnosis.analysis.model_trace, diagnosis.analysis.quantification
    if stored is not None or estimate is None:
        return stored
    return model_trace(op, pv, ts, estimate, diagnosis.analysed_period)


def _signature(session: SessionDep, state: StateDep, loop: Loop, run: AnalysisRun
               ) -> plots.Figure:
    window = _analysed_window(session, state, loop, run)
    if window.op is None or window.pv is None:
        raise HTTPException(404, "The valve signature needs both OP and PV tags")
    diagnosis = StoredDiagnosis.from_dict(run.result)
    period = diagnosis.analysed_period
    period_samples = None if period is None else period / window.ts
    return plots.signature_figure(
        window.op, window.pv, mv=window.mv,
        pv_fit=(diagnosis.analysis.ellipse
                or _ellipse(window.op, window.pv, period_samples)),
        mv_fit=_ellipse(window.op, window.mv, period_samples),
        model=_fitted_model(window.op, window.pv, window.ts, diagnosis),
        title=_title(loop, "valve signature", window.t[0], window.t[-1]),
    )


def _spectrum(session: SessionDep, state: StateDep, loop: Loop, run: AnalysisRun
              ) -> plots.Figure:
    window = _analysed_window(session, state, loop, run)
    period = StoredDiagnosis.from_dict(run.result).analysed_period
    return plots.spectrum_figure(
        window.op, window.pv, window.ts, period_s=period,
        title=_title(loop, "spectrum and ACF", window.t[0], window.t[-1]),
    )


def _nyquist(loop: Loop, run: AnalysisRun) -> plots.Figure:
    try:
        model = identified_loop(loop.config, StoredDiagnosis.from_dict(run.result))
    except ModelUnavailableError as exc:
        raise HTTPException(404, str(exc)) from None
    try:
        prediction = predict_limit_cycles(model.process, model.controller, model.valve,
                                          hold_delay=model.hold_delay, describing="equivalent")
        stable = prediction.stable_cycles
        curves = nyquist_curves(model.process, model.controller, model.valve,
                                hold_delay=model.hold_delay, describing="equivalent",
                                limit_cycle=stable[0] if stable else None)
    except (ModelSpecError, ValueError) as exc:
        raise HTTPException(404, str(exc)) from None
    return plots.nyquist_figure(
        curves, prediction=prediction,
        # the analysed window's own estimate, not the valve's combined size (QA)
        title=f"{_name(loop)}: Nyquist plot, identified model; this window: "
              f"S {model.size[0]:.2f} %, J {model.size[1]:.2f} %",
    )


def _history(session: SessionDep, loop: Loop) -> plots.Figure:
    runs = list(session.scalars(
        select(AnalysisRun).where(AnalysisRun.loop_id == loop.id, AnalysisRun.status == "ok")
        .order_by(AnalysisRun.id.desc()).limit(HISTORY_RUNS)
    ))[::-1]
    if not runs:
        raise HTTPException(404, f"No analysis of loop {loop.id} yet")

    return plots.history_figure(
        _values([r.started_at for r in runs]), _values([r.health for r in runs]),
        _values([r.S for r in runs]), _values([r.J for r in runs]),
        title=f"{_name(loop)}: health and S, J of {len(runs)} analyses",
    )


class ModelCheckOverlay(BaseModel):
    """The ``overlay`` of a model check: measured and simulated PV per sample."""

    t: list[float]
    pv: list[float | None]
    pv_base: list[float | None]
    pv_extended: list[float | None]
    scored: list[bool]


class ModelCheckCause(BaseModel):
    """The ``cause`` of a model check: the effect that extends the base model."""

    effect: str


class ModelCheckPlotRequest(BaseModel):
    """The parts of a ``POST /loops/{id}/model-check`` answer that the plot draws."""

    overlay: ModelCheckOverlay
    cause: ModelCheckCause


def _image(figure: plots.Figure, loop_id: str, kind: str, image_format: str) -> Response:
    if image_format == "png":
        body: bytes = plots.render_png(figure)
    else:
        body = plots.render_svg(figure).encode()
    return Response(
        body, media_type=MEDIA_TYPES[image_format],
        headers={"Cache-Control": "no-store",
                 "Content-Disposition": f'inline; filename="{loop_id}-{kind}.{image_format}"'},
    )


@router.post(
    "/{loop_id}/plots/model-check",
    response_class=Response,
    responses={200: {"content": IMAGE_CONTENT,
                     "description": "measured against simulated PV, and the errors"},
               404: {"description": "unknown loop"},
               422: {"description": "overlay series of different lengths"}},
)
def model_check_plot(
    loop_id: str,
    body: ModelCheckPlotRequest,
    session: SessionDep,
    _: Reader,
    image_format: Annotated[PlotFormat, Query(alias="format")] = "svg",
) -> Response:
    """The overlay of a model check of the loop as SVG (default) or PNG."""
    loop = _loop_or_404(session, loop_id)
    overlay, cause = body.overlay, body.cause
    if not overlay.t:
        raise HTTPException(422, "The overlay has no samples")
    try:
        figure = plots.model_check_figure(
            overlay.t, _values(overlay.pv), _values(overlay.pv_base),
            _values(overlay.pv_extended), overlay.scored,
            title=f"{_name(loop)}: model check, " + (
                "no effect found" if cause.effect == "none"
                else f"extended with {cause.effect.replace('_', ' ')}"),
        )
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    return _image(figure, loop_id, "model-check", image_format)


@router.get(
    "/{loop_id}/plots/{kind}",
    response_class=Response,
    responses={200: {"content": IMAGE_CONTENT,
                     "description": "the plot"},
               404: {"description": "unknown loop, or the plot cannot be drawn yet (why)"}},
)
def loop_plot(
    loop_id: str,
    kind: PlotKind,
    session: SessionDep,
    state: StateDep,
    _: Reader,
    image_format: Annotated[PlotFormat, Query(alias="format")] = "svg",
    start: Annotated[TimeQuery, Query(description="trend: UNIX s")] = None,
    end: Annotated[TimeQuery, Query(description="trend: UNIX s (default now)")] = None,
) -> Response:
    """A plot of the loop as SVG (default) or PNG; see the module docstring for the kinds."""
    loop = _loop_or_404(session, loop_id)
    if kind == "trend":
        figure = _trend(session, state, loop, start, end)
    elif kind == "history":
        figure = _history(session, loop)
    else:
        run = _latest_run(session, loop_id)
        if kind == "signature":
            figure = _signature(session, state, loop, run)
        elif kind == "spectrum":
            figure = _spectrum(session, state, loop, run)
        else:
            figure = _nyquist(loop, run)
    return _image(figure, loop_id, kind, image_format)
