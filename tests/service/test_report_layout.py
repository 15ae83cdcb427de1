"""The bad-actor PDF keeps every word on the page: a loop's name cut mid-word without a
mark ("AIC-502 Side-stream ethano") and a why that ran past the page's right edge (the
demo plant's notes with the Harris dead time's reason are 300 mm long on a 277 mm line)."""

from __future__ import annotations

import io

from fpdf import FPDF
from pypdf import PdfReader

from service.api.schemas.loops import BadActorPublic
from service.report import BadActorReport, ReportLine, report_pdf

DEAD_TIME = ("unknown: no set-point moves beyond noise and no OP moves in manual in the "
             "window; under feedback alone the dead time cannot be identified")


def line(rank: int, loop_id: str, name: str) -> ReportLine:
    row = BadActorPublic(
        id=loop_id, name=name, unit="column", valve_asset="FV-502", importance="critical",
        health=0.5, oscillating=True, period_s=199.0, verdict="stiction", confidence=0.99,
        S=4.2, J=2.0, analysed_at=1.0e9, active_alarms=1, score=175.8, severity=0.88,
        bad_share=1.0, runs=2, bad_runs=2, worst="diagnosis",
        why="bad in 2 of 2 runs (100 %) over 7d; worst: diagnosis (health) 0.88; importance "
            "critical (x2)")
    kpis = {"oscillation_index": 1.0, "error_std": 1.43, "travel_per_day": 3523.0,
            "reversals_per_day": 864.0, "saturation": 0.0, "dead_time_note": DEAD_TIME}
    return ReportLine(rank, row, kpis, ["#3 FV-502"], [(1.0e9, 0.88)])


def fragments(data: bytes) -> tuple[list[tuple[float, float, str]], float]:
    """Every text fragment of the first page: its x, its font size and its text."""
    page = PdfReader(io.BytesIO(data)).pages[0]
    found: list[tuple[float, float, str]] = []

    def visit(text: str, cm: list[float], tm: list[float], font: object, size: float) -> None:
        if text.strip():
            found.append((tm[4] * cm[0] + cm[4], size * tm[0], text))

    page.extract_text(visitor_text=visit)
    return found, float(page.mediabox.width)


def test_long_names_and_whys_stay_on_the_page_and_whole() -> None:
    report = BadActorReport("7d", 0.0, 7 * 86400.0, [
        line(1, "AIC-502", "Side-stream ethanol composition"), line(2, "FIC-105", "Steam")])
    data = report_pdf(report)
    text = " ".join(PdfReader(io.BytesIO(data)).pages[0].extract_text().split())
    assert "AIC-502 Side-stream ethanol composition" in text  # whole, in its note
    assert "Side-stream ethano " not in text + " "
    assert "FIC-105 Steam critical" in text  # a name that fits stays in its cell
    assert DEAD_TIME.split()[-1] in text
    measure = FPDF(unit="pt")
    measure.add_page()
    found, width = fragments(data)
    for x, size, fragment in found:
        measure.set_font("Helvetica", "", size or 8)
        # within the right margin (10 mm), a point's rounding aside
        assert x + measure.get_string_width(fragment) <= width - 27, fragment
