"""The simulated demo plant: loops with known faults, fed in through the ingest path.

Each demo loop is a closed loop of :mod:`analytics.synthetic_cases` with a
known cause: two sticky valves (tickets expected), an over-tuned loop and a
loop shaken by an upstream disturbance (oscillation alarms, but no valve to
blame), and healthy loops.  The first ``history_s`` of every simulation is
stamped in the past and ingested at once -- as a historian backfill would be
-- so the first analysis already has a full window; the rest is released in
real time by :class:`DemoFeeder`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from analytics.synthetic_cases import SyntheticCase, synthetic_library
from service.config import PlantConfig

__all__ = ["DEMO_LOOPS", "DemoFeeder", "DemoPlant", "demo_plant_config"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DemoLoop:
    """A demo loop: its configuration entry and the simulated case behind it."""

    id: str
    name: str
    case: str  # name of the analytics.synthetic_cases case
    valve_asset: str
    importance: str
    expected: str  # what the diagnosis should find


DEMO_LOOPS = (
    DemoLoop("FIC-101", "Feed flow", "flow-kano-S4-J2-ts1", "FV-101", "high",
             "sticky valve (Kano S=4 %, J=2 %): alarm and ticket"),
    DemoLoop("FIC-102", "Reflux flow", "flow-aggressive-ts1", "FV-102", "medium",
             "over-tuned controller: oscillation alarm, no ticket"),
    DemoLoop("TIC-201", "Reactor temperature", "temp-sine500s-ts2", "TV-201", "high",
             "upstream disturbance (500 s): oscillation alarm, no ticket"),
    DemoLoop("LIC-301", "Drum level", "level-noise-ts1", "LV-301", "medium", "healthy"),
    DemoLoop("FIC-105", "Steam flow", "flow-he-S8-J4-ts1", "FV-105", "critical",
             "sticky valve (He fs=6 %, fd=2 %): alarm and ticket"),
    DemoLoop("PIC-401", "Header pressure", "flow-noise-ts0.5", "PV-401", "low", "healthy"),
)


def _case(name: str, samples: int) -> SyntheticCase:
    return next(c for c in synthetic_library(samples) if c.name == name)


def demo_plant_config() -> PlantConfig:
    """The plant configuration of the demo loops (signals already in % of span)."""
    loops = []
    for d in DEMO_LOOPS:
        case = _case(d.case, 100)
        loops.append({
            "id": d.id, "name": d.name, "unit": "demo",
            "tags": {s: f"{d.id}.{s.upper()}" for s in ("op", "pv", "sp")},
            "ranges": {"op": (0.0, 100.0), "pv": (0.0, 100.0)},
            "ts": case.ts, "process_type": case.process_type, "valve_asset": d.valve_asset,
            "location": f"DEMO-{d.id[:3]}", "importance": d.importance,
            "controller": {"type": "PI", "Kc": case.controller.kp,
                           "Ti": case.controller.kp / case.controller.ki},
        })
    return PlantConfig.model_validate(
        {"units": [{"id": "demo", "name": "Demo plant (simulated)"}], "loops": loops}
    )


class DemoPlant:
    """Precomputed simulations of the demo loops mapped onto wall-clock time.

    Sample ``k`` of a loop is stamped ``origin + k ts`` with ``origin = start
    - history_s``: the first ``history_s`` lie in the past at ``start``.
    """

    def __init__(self, *, start: float, history_s: float = 3600.0,
                 live_s: float = 6 * 3600.0) -> None:
        self.origin = start - history_s
        self.duration_s = history_s + live_s
        self._series: dict[str, tuple[float, dict[str, np.ndarray]]] = {}
        for d in DEMO_LOOPS:
            probe = _case(d.case, 100)
            samples = int(self.duration_s / probe.ts)
            result = _case(d.case, samples).simulate()
            self._series[d.id] = (
                probe.ts, {"OP": result.op[0], "PV": result.pv[0], "SP": result.sp[0]}
            )

    def batch(self, t0: float, t1: float) -> list[dict[str, Any]]:
        """Samples stamped in ``(t0, t1]`` as an ingest batch (PI Web API shape)."""
        batch = []
        for loop_id, (ts, signals) in self._series.items():
            k0 = max(int(np.floor((t0 - self.origin) / ts)) + 1, 0)
            k1 = min(int(np.floor((t1 - self.origin) / ts)), len(signals["OP"]) - 1)
            if k1 < k0:
                continue
            times = self.origin + ts * np.arange(k0, k1 + 1)
            for signal, values in signals.items():
                batch.append({
                    "tag": f"{loop_id}.{signal}",
                    "items": [{"timestamp": float(t), "value": float(v)}
                              for t, v in zip(times, values[k0: k1 + 1], strict=True)],
                })
        return batch


class DemoFeeder:
    """Releases the demo plant's samples into ``ingest`` as wall-clock time passes."""

    def __init__(self, plant: DemoPlant, ingest: Callable[[list[dict[str, Any]]], object],
                 *, clock: Callable[[], float] = time.time, period_s: float = 1.0) -> None:
        self.plant = plant
        self.ingest = ingest
        self.clock = clock
        self.period_s = period_s
        self._released = plant.origin - 1.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def release(self) -> int:
        """Ingest everything stamped up to now; returns the number of samples."""
        now = self.clock()
        batch = self.plant.batch(self._released, now)
        if batch:
            self.ingest(batch)
        self._released = now  # only once ingested: a failed release is retried
        return sum(len(entry["items"]) for entry in batch)

    def start(self) -> None:
        """Backfill the history, then release new samples every ``period_s``."""
        self.release()

        def run() -> None:
            while not self._stop.wait(self.period_s):
                try:
                    self.release()
                except Exception:  # a failed release is retried with the next one
                    log.exception("demo feeder: ingest failed")

        self._thread = threading.Thread(target=run, name="loopwatch-demo-feeder", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop releasing samples."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
