"""The demo: the simulated plant served over OPC UA and Modbus on loopback, and back-filled.

``loopwatch serve`` without a plant file watches the plant of
:mod:`connectors.plant_sim` (six single loops with known faults and a 3x3
column with one sticky valve).  :class:`DemoFeeder` serves it on free
loopback ports from a thread of the service, and the service reads it
through its connectors like any plant.  So that the first analyses have full
windows (the latest, and the earlier ones the ticket rule confirms on), the
last ``history_s`` of the plant is ingested at start, as a
historian back-fill would be, and once the connectors deliver, each tag's
samples up to its first live one: the window runs on from history to live
data without a gap.

The simulation starts ``history_s`` before the service, so the first
analyses of every start see the same simulated history.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from connectors.base import SampleSink
from connectors.plant_sim import PLANT_LOOPS, PlantSimulator
from service.config import PlantConfig

__all__ = ["DEMO_LOOPS", "DemoFeeder", "demo_plant_config"]

log = logging.getLogger(__name__)

DEMO_LOOPS = PLANT_LOOPS
"""The loops of the demo plant."""

LIVE_HORIZON_S = 12 * 3600.0
"""Plant time simulated beyond the history before the runs start over."""


def demo_plant_config() -> PlantConfig:
    """The demo plant's units and loops, without connectors: for processes not serving it."""
    spec = PlantSimulator(modbus_port=None).plant_config()
    del spec["connectors"]
    return PlantConfig.model_validate(spec)


class DemoFeeder:
    """Serves the demo plant on free loopback ports and back-fills its history.

    :meth:`start` serves the plant and ingests its last ``history_s`` before
    the connectors start, so the back-fill's load does not delay their first
    polls.  The connectors deliver through a :meth:`live_sink`, which notes
    each tag's first live sample; :meth:`close_seam` waits for them and
    ingests what the plant served between the back-fill and them.

    Parameters
    ----------
    history_s : float
        Seconds of plant history back-filled (the windows a sticky valve's ticket needs,
        :meth:`service.scheduling.rounds.RoundGrid.due_rounds`).
    max_batch_samples : int
        The most samples one ingest batch may hold.
    clock : callable
        Wall clock, UNIX seconds.
    live_wait_s : float
        How long :meth:`close_seam` waits for the first live samples.
    """

    def __init__(self, *, history_s: float, max_batch_samples: int,
                 clock: Callable[[], float] = time.time, live_wait_s: float = 30.0) -> None:
        self.history_s = history_s
        self.max_batch_samples = max_batch_samples
        self.clock = clock
        self.live_wait_s = live_wait_s
        self.plant = PlantSimulator(opcua_port=0, modbus_port=0, origin=clock() - history_s,
                                    clock=clock, horizon_s=history_s + LIVE_HORIZON_S)
        spec = self.plant.plant_config()
        self.plant_config = PlantConfig.model_validate(spec)
        self.tags = [tag for loop in spec["loops"] for tag in loop["tags"].values()]
        self.backfilled_until: float | None = None
        """UNIX time up to which :meth:`start` back-filled."""
        self.backfilled_from: float | None = None
        """UNIX time from which :meth:`start` back-filled."""
        self._first_live: dict[str, float] = {}
        self._lock = threading.Lock()

    def live_sink(self, ingest: SampleSink) -> SampleSink:
        """The connectors' sink: notes each tag's first live sample, then calls ``ingest``."""

        def sink(batch: list[dict[str, Any]]) -> object:
            with self._lock:
                for entry in batch:
                    stamps = [item["timestamp"] for item in entry["items"]]
                    if stamps and entry["tag"] not in self._first_live:
                        self._first_live[entry["tag"]] = min(stamps)
            return ingest(batch)

        return sink

    @property
    def history_text(self) -> str:
        """The back-filled history in words, as the start banner and the log say it.

        >>> feeder = DemoFeeder(history_s=7200, max_batch_samples=1000, clock=lambda: 0.0)
        >>> feeder.history_text
        'the last 2 h (7200 s)'
        >>> feeder.backfilled_from, feeder.backfilled_until = -600.0, 0.0  # after a restart
        >>> feeder.history_text
        'the last 10 min (600 s), after the samples stored by the run before'
        """
        span = self.history_s
        if self.backfilled_from is not None and self.backfilled_until is not None:
            span = self.backfilled_until - self.backfilled_from
        hours, minutes = divmod(round(span / 60), 60)
        words = " ".join(part for part in (f"{hours} h" if hours else "",
                                           f"{minutes} min" if minutes else "") if part)
        text = f"the last {words or f'{span:.0f} s'} ({span:.0f} s)"
        return text if span >= self.history_s else text + (
            ", after the samples stored by the run before")

    def start(self, ingest: SampleSink, *, after: float | None = None) -> int:
        """Serve the plant and ingest its last ``history_s``; the number of samples.

        ``after`` is the latest sample the store already holds of the plant's tags (a
        restart within the history): the back-fill starts after it, since this run's
        plant is simulated from another origin and its samples would interleave with
        the stored ones (two plants in one window); the seam is a plant restart.
        """
        self.plant.start_in_thread()
        now = self.clock()
        since = now - self.history_s if after is None else max(now - self.history_s, after)
        samples = self._ingest_history(ingest, since, dict.fromkeys(self.tags, now))
        self.backfilled_from, self.backfilled_until = since, now
        log.info("demo plant: back-filled %d samples of %s", samples, self.history_text)
        return samples

    def close_seam(self, ingest: SampleSink) -> int:
        """Ingest what was served between the back-fill and each tag's first live sample.

        Waits up to ``live_wait_s`` for a live sample of every tag; a tag
        still without one is back-filled up to now (and named in a warning).
        Returns the number of samples ingested.
        """
        if self.backfilled_until is None:
            raise RuntimeError("the demo plant has not started")
        deadline = time.monotonic() + self.live_wait_s
        while len(self._first_live) < len(self.tags) and time.monotonic() < deadline:
            time.sleep(0.05)
        now = self.clock()
        with self._lock:
            until = {tag: self._first_live.get(tag, now) for tag in self.tags}
        silent = sorted(tag for tag in self.tags if tag not in self._first_live)
        if silent:
            log.warning("demo plant: no live sample of %s after %g s; back-filled up to now",
                        ", ".join(silent), self.live_wait_s)
        return self._ingest_history(ingest, self.backfilled_until, until)

    def _ingest_history(self, ingest: SampleSink, since: float, until: dict[str, float]) -> int:
        samples = 0
        for batch in self.plant.history(since, until, max_samples=self.max_batch_samples):
            ingest(batch)
            samples += sum(len(entry["items"]) for entry in batch)
        return samples

    def stop(self) -> None:
        """Stop serving the plant."""
        self.plant.stop_thread()
