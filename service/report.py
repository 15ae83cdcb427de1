"""The bad-actor report for a weekly meeting: the plant's worst loops, as CSV or PDF.

:func:`build_report` reads the ranking of ``/plant/bad-actors``
(:mod:`service.bad_actors`) over a period from the store, with each loop's
latest diagnosis and KPIs, its open tickets and the trend of its severity
over the period (one point per analysis window, the runs the score counts).
:func:`report_csv` and :func:`report_pdf` write it; ``GET
/api/v1/reports/bad-actors`` and ``loopwatch report`` serve them.

The PDF is drawn with fpdf2: pure Python (no compiled parts to build on a
plant's server), maintained, and it draws lines and text directly, which is
all a table with sparklines needs (no plotting library in between).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from fpdf import FPDF
from sqlalchemy import select
from sqlalchemy.orm import Session

from service.api.schemas.loops import BadActorPublic
from service.bad_actors import BAD_SEVERITY, run_severity
from service.ranking import bad_actor_rows, counted_runs
from service.store.models import Ticket
from service.stored import StoredKpis

__all__ = ["COLUMNS", "BadActorReport", "ReportLine", "build_report", "report_csv",
           "report_pdf"]

COLUMNS = (
    "rank", "loop", "name", "unit", "importance", "score", "severity", "bad_share", "runs",
    "bad_runs", "worst", "why", "health", "oscillating", "period_s", "verdict",
    "oscillation_index", "harris_ratio", "harris_dead_time", "error_std", "travel_per_day",
    "reversals_per_day", "saturation", "service_factor", "open_tickets",
)
"""The CSV columns; the KPIs (% of span) are those of the latest analysis run;
``harris_dead_time`` says where the Harris index's dead time came from
(``configured``, ``identified from set-point steps``, ``unknown: ...``)."""

OPEN_TICKET_STATES = ("open", "acknowledged", "scheduled")


@dataclass(frozen=True)
class ReportLine:
    """One loop of the report.

    Attributes
    ----------
    rank : int
    loop : BadActorPublic
        Its latest state and score over the period.
    kpis : dict
        The KPIs of its latest run (:meth:`analytics.kpi.LoopKpis.to_dict`; empty without).
    tickets : list of str
        Its open tickets, ``"#id valve"``.
    trend : list of (float, float)
        ``(started_at, severity)`` of each counted run of the period, oldest first
        (:func:`service.bad_actors.run_severity`).
    """

    rank: int
    loop: BadActorPublic
    kpis: dict[str, Any]
    tickets: list[str]
    trend: list[tuple[float, float]]


@dataclass(frozen=True)
class BadActorReport:
    """The report over ``(since, until]``; ``lines`` worst first."""

    period: str
    since: float
    until: float
    lines: list[ReportLine]


def _open_tickets(session: Session) -> dict[str, list[str]]:
    tickets: dict[str, list[str]] = {}
    for ticket_id, loop_id, valve in session.execute(
        select(Ticket.id, Ticket.loop_id, Ticket.valve_asset)
        .where(Ticket.state.in_(OPEN_TICKET_STATES)).order_by(Ticket.id)
    ):
        tickets.setdefault(loop_id, []).append(f"#{ticket_id} {valve}")
    return tickets


def build_report(session: Session, *, until: float, period_s: float, period: str,
                 window_s: float, limit: int) -> BadActorReport:
    """The ``limit`` worst loops over the ``period_s`` before ``until`` (``period`` names it,
    e.g. ``7d``); ``window_s`` is the analysis window, the score's unit of time."""
    since = until - period_s
    runs = counted_runs(session, since, until, window_s)
    ranked = bad_actor_rows(session, since, until, period, window_s, runs)[:limit]
    tickets = _open_tickets(session)
    lines = [ReportLine(rank, row, row.kpis or {}, tickets.get(row.id, []),
                        [(t, run_severity(health, k)) for t, health, k in runs.get(row.id, [])])
             for rank, row in enumerate(ranked, start=1)]
    return BadActorReport(period, since, until, lines)


def _number(value: Any, digits: int = 4) -> str:
    return "" if value is None else f"{float(value):.{digits}g}"


def _figures(stored: dict[str, Any]) -> dict[str, Any]:
    """The latest KPIs the report shows, by column name (None where not computed)."""
    kpis = StoredKpis.from_dict(stored)
    return {
        "oscillation_index": kpis.oscillation_index,
        "harris_ratio": kpis.harris_ratio,
        "harris_dead_time": kpis.dead_time_note,
        "error_std": kpis.error_std,
        "travel_per_day": kpis.travel_per_day,
        "reversals_per_day": kpis.reversals_per_day,
        "saturation": kpis.saturation,
        "service_factor": kpis.service_factor,
    }


def report_csv(report: BadActorReport) -> str:
    """The report as CSV, one row per loop (:data:`COLUMNS`)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(COLUMNS)
    for line in report.lines:
        row = line.loop
        writer.writerow([
            line.rank, row.id, row.name, row.unit or "", row.importance, _number(row.score),
            _number(row.severity), _number(row.bad_share), row.runs, row.bad_runs,
            row.worst or "", row.why, _number(row.health),
            "" if row.oscillating is None else str(row.oscillating).lower(),
            _number(row.period_s), row.verdict or "",
            *(v if isinstance(v, str) else _number(v) for v in _figures(line.kpis).values()),
            "; ".join(line.tickets),
        ])
    return out.getvalue()


def _latin1(text: str) -> str:
    """The PDF's core fonts hold Latin-1 only: other characters become ``?``."""
    return text.encode("latin-1", "replace").decode("latin-1")


def _fit(pdf: FPDF, text: str, width: float) -> str:
    """``text`` shortened to fit a cell ``width`` mm wide in the current font, with
    "..." where it was cut (a cut mid-word without a mark read as a wrong name)."""
    room = width - 2 * pdf.c_margin
    if pdf.get_string_width(text) <= room:
        return text
    while text and pdf.get_string_width(text + "...") > room:
        text = text[:-1]
    return text.rstrip() + "..."


def _stamp(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d %H:%M UTC")


def _sparkline(pdf: FPDF, trend: list[tuple[float, float]], x: float, y: float, w: float,
               h: float, since: float, until: float) -> None:
    """Severity 0..1 over the period as a polyline in the box (x, y, w, h); the
    :data:`service.bad_actors.BAD_SEVERITY` line dotted."""
    pdf.set_draw_color(200, 200, 200)
    pdf.set_line_width(0.1)
    pdf.rect(x, y, w, h)
    pdf.set_dash_pattern(dash=0.5, gap=0.5)
    pdf.line(x, y + h * (1 - BAD_SEVERITY), x + w, y + h * (1 - BAD_SEVERITY))
    pdf.set_dash_pattern()
    if not trend:
        return
    span = max(until - since, 1e-9)
    points = [(x + w * min(max((t - since) / span, 0.0), 1.0), y + h * (1 - min(s, 1.0)))
              for t, s in trend]
    pdf.set_draw_color(180, 30, 30)
    pdf.set_line_width(0.35)
    if len(points) == 1:
        pdf.circle(points[0][0], points[0][1], 0.6, style="F")
    else:
        pdf.polyline(points)


HEADER = (("#", 8), ("loop", 44), ("imp.", 14), ("score", 14), ("health", 13),
          ("verdict", 22), ("osc.", 11), ("Harris", 13), ("err. sd", 13), ("travel/d", 16),
          ("rev./d", 14), ("sat.", 11), ("auto", 11), ("trend (severity)", 40),
          ("open tickets", 33))
"""PDF table columns and their widths (mm) on landscape A4."""


def report_pdf(report: BadActorReport) -> bytes:
    """The report as a landscape A4 PDF: a table of the worst loops with their latest
    KPIs, the score's why, diagnosis and open tickets, and a sparkline of each loop's
    severity over the period."""
    pdf = FPDF(orientation="L", unit="mm", format="A4")
    pdf.set_auto_page_break(auto=True, margin=12)
    pdf.set_title(f"loopwatch bad-actor report {report.period}")
    pdf.set_creator("loopwatch")
    pdf.add_page()
    pdf.set_font("Helvetica", "B", 15)
    pdf.cell(0, 8, f"Bad-actor report: the worst loops over {report.period}",
             new_x="LMARGIN", new_y="NEXT")
    pdf.set_font("Helvetica", "", 9)
    pdf.multi_cell(0, 5, _latin1(
        f"{_stamp(report.since)} to {_stamp(report.until)}. Score = 100 x severity x "
        "importance weight x share of the period's runs that were bad; the trend is each "
        "analysis window's severity (dotted: bad from 0.3)."), new_x="LMARGIN", new_y="NEXT")
    pdf.ln(2)

    def header() -> None:
        pdf.set_font("Helvetica", "B", 8)
        pdf.set_fill_color(230, 230, 230)
        for title, width in HEADER:
            pdf.cell(width, 6, title, border=1, fill=True)
        pdf.ln()

    header()
    if not report.lines:
        pdf.set_font("Helvetica", "I", 9)
        pdf.cell(0, 8, "No loop is configured.", new_x="LMARGIN", new_y="NEXT")
    row_h, note_h = 8.0, 4.5
    for line in report.lines:
        row, f = line.loop, StoredKpis.from_dict(line.kpis)
        diagnosis = (f"oscillating, period {row.period_s:.0f} s" if row.oscillating
                     and row.period_s is not None else
                     "oscillating" if row.oscillating else "not oscillating"
                     if row.oscillating is not None else "not analysed")
        dead_time = f"; Harris dead time {f.dead_time_note}" if f.dead_time_note else ""
        pdf.set_font("Helvetica", "", 8)
        name = f"{row.id} {row.name}"
        named = "" if _fit(pdf, _latin1(name), HEADER[1][1]) == _latin1(name) else f"{name}: "
        # The note wraps onto as many lines as it needs: one line ran off the page's edge.
        note = _latin1(f"{named}{row.why}; {diagnosis}{dead_time}")
        pdf.set_font("Helvetica", "I", 7)
        lines = pdf.multi_cell(0, note_h, note, dry_run=True, output="LINES")
        note_lines = len(lines) if isinstance(lines, list) else 1
        if pdf.get_y() + row_h + note_h * note_lines > pdf.h - pdf.b_margin:
            pdf.add_page()
            header()
        cells = [
            str(line.rank), f"{row.id} {row.name}", row.importance, f"{row.score:.1f}",
            _number(row.health, 3), row.verdict or "", _number(f.oscillation_index, 2),
            _number(f.harris_ratio, 2), _number(f.error_std, 3),
            _number(f.travel_per_day, 4), _number(f.reversals_per_day, 4),
            _number(f.saturation, 2), _number(f.service_factor, 2),
        ]
        pdf.set_font("Helvetica", "", 8)
        y = pdf.get_y()
        for text, (_, width) in zip(cells, HEADER, strict=False):
            pdf.cell(width, row_h, _fit(pdf, _latin1(text), width), border="LTB")
        x = pdf.get_x()
        spark_w = HEADER[-2][1]
        pdf.cell(spark_w, row_h, "", border="LTB")
        _sparkline(pdf, line.trend, x + 1, y + 1, spark_w - 2, row_h - 2,
                   report.since, report.until)
        pdf.set_xy(x + spark_w, y)
        pdf.cell(HEADER[-1][1], row_h, _latin1(", ".join(line.tickets) or "none"), border=1)
        pdf.ln()
        pdf.set_font("Helvetica", "I", 7)
        pdf.multi_cell(0, note_h, note, border="LRB", new_x="LMARGIN", new_y="NEXT")
    return bytes(pdf.output())
