"""Service metrics in the Prometheus text exposition format.

Counters are plain integers guarded by a lock (the API, the scheduler thread
and the demo feeder all count); gauges are read from the store when scraped.
"""

from __future__ import annotations

import threading
from collections import defaultdict

__all__ = ["Metrics"]


class Metrics:
    """Named counters with labels, rendered for ``GET /metrics``."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counters: dict[tuple[str, tuple[tuple[str, str], ...]], float] = defaultdict(float)
        self._help: dict[str, str] = {}

    def describe(self, name: str, help_text: str) -> None:
        """Register the HELP text of a metric."""
        self._help[name] = help_text

    def inc(self, name: str, amount: float = 1.0, **labels: str) -> None:
        """Add ``amount`` to counter ``name`` with ``labels``."""
        key = (name, tuple(sorted(labels.items())))
        with self._lock:
            self._counters[key] += amount

    def value(self, name: str, **labels: str) -> float:
        """Current value of a counter (0 if never incremented)."""
        with self._lock:
            return self._counters.get((name, tuple(sorted(labels.items()))), 0.0)

    def render(self, gauges: dict[str, float] | None = None) -> str:
        """The exposition text: every counter, then the given gauges (``name`` or
        ``name{label="value"}``)."""
        lines: list[str] = []
        with self._lock:
            items = sorted(self._counters.items())
        seen: set[str] = set()
        for (name, labels), value in items:
            if name not in seen:
                seen.add(name)
                if name in self._help:
                    lines.append(f"# HELP {name} {self._help[name]}")
                lines.append(f"# TYPE {name} counter")
            label_text = ",".join(f'{k}="{v}"' for k, v in labels)
            number = _exposition_number(value)
            lines.append(f"{name}{{{label_text}}} {number}" if labels else f"{name} {number}")
        for name, value in sorted((gauges or {}).items()):
            base = name.split("{", 1)[0]  # a gauge may carry labels: name{label="value"}
            if base not in seen:
                seen.add(base)
                lines.append(f"# TYPE {base} gauge")
            lines.append(f"{name} {_exposition_number(value)}")
        return "\n".join(lines) + "\n"


def _exposition_number(value: float) -> str:
    """Every digit of ``value``: whole numbers as integers, others as Python's shortest
    round-trip form (``:g`` would print 1234567 samples as 1.23457e+06)."""
    return str(int(value)) if float(value).is_integer() else repr(float(value))
