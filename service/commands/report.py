"""loopwatch report: the bad-actor report of the plant's store as a PDF or CSV file.

``loopwatch report --since 7d --out week.pdf [--until T] [--limit N]`` writes the worst loops of the
last week with their KPIs, diagnosis, open tickets and severity sparklines
(:mod:`service.report`, the same report as ``GET
/api/v1/reports/bad-actors``), read from the store the service writes
(``LOOPWATCH_DATABASE_URL``, else the SQLite file in ``LOOPWATCH_DATA_DIR``;
the score's unit of time is ``LOOPWATCH_WINDOW_S``).  The file's suffix
chooses the format.
"""

from __future__ import annotations

import argparse
import re
import time
from pathlib import Path

from sqlalchemy.engine import make_url
from sqlalchemy.exc import SQLAlchemyError

from service.commands import CliError, Subcommands

__all__ = ["register", "run"]


def register(commands: Subcommands) -> None:
    """Add ``report`` to the ``loopwatch`` subcommands."""
    parser = commands.add_parser(
        "report", help="write the bad-actor report (PDF or CSV) from the service's store",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
    )
    parser.add_argument("--since", default="7d",
                        help="the period back from now: 7d, 36h (at most 92d; default 7d)")
    parser.add_argument("--out", type=Path, required=True, help="FILE.pdf or FILE.csv")
    parser.add_argument("--limit", type=int, default=20, help="loops in the report (default 20)")
    parser.add_argument("--until", type=float, default=None,
                        help="end of the period, UNIX s (default now): an earlier week's report")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Write the report; 0 on success (user errors raise :class:`CliError`)."""
    from pydantic import ValidationError

    from service.config import Settings
    from service.ranking import PERIOD_PATTERN, period_length
    from service.report import build_report, report_csv, report_pdf
    from service.store.db import Store

    fmt = args.out.suffix.lower().lstrip(".")
    if fmt not in ("pdf", "csv"):
        raise CliError(f"--out {args.out}: the file must end in .pdf or .csv")
    if not re.fullmatch(PERIOD_PATTERN, args.since):
        raise CliError(f"--since {args.since!r}: a period such as 7d or 36h")
    try:
        period_s = period_length(args.since)
    except ValueError as exc:
        raise CliError(f"--since {args.since}: {exc}") from None
    if args.limit < 1:
        raise CliError("--limit must be at least 1")
    try:
        settings = Settings()
    except ValidationError as exc:
        raise CliError(f"settings: {exc.errors()[0]['msg']}") from None
    url = settings.resolved_database_url
    database = make_url(url).database
    if url.startswith("sqlite") and database and not Path(database).exists():
        raise CliError(f"no store at {database}: run `loopwatch serve` first, or set "
                       "LOOPWATCH_DATA_DIR / LOOPWATCH_DATABASE_URL")
    store = Store(url, run_migrations=False)
    try:
        with store.session() as session:
            until = time.time() if args.until is None else args.until
            report = build_report(session, until=until, period_s=period_s,
                                  period=args.since, window_s=settings.window_s,
                                  limit=args.limit)
    except SQLAlchemyError as exc:
        raise CliError(f"the store cannot be read: {exc.__class__.__name__}: "
                       f"{str(exc).splitlines()[0]}") from None
    finally:
        store.close()
    try:
        if fmt == "pdf":
            args.out.write_bytes(report_pdf(report))
        else:
            args.out.write_text(report_csv(report))
    except OSError as exc:
        raise CliError(f"--out {args.out}: {exc.strerror}") from None
    print(f"{args.out}: {len(report.lines)} loops over {args.since}")
    return 0
