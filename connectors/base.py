"""What every connector shares: where samples go, and how to wait before reconnecting.

A connector turns protocol data into ingest batches of the PI Web API shape
(``[{"tag", "items": [{"timestamp", "value", "good"}]}]``) and hands them to
a :class:`SampleSink` -- in the service that is ``AppState.ingest``, which
stores them (idempotently, counting every refusal) and feeds the rolling
buffers.  While a connection is down nothing is stored, so the window shows
a gap that the data-quality screen reports; the connector counts and logs
the outage.
"""

from __future__ import annotations

import random
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Protocol

__all__ = ["Backoff", "SampleSink", "item"]


class SampleSink(Protocol):
    """Receives ingest batches; returns whatever the receiver reports (ignored here)."""

    def __call__(self, batch: list[dict[str, Any]], /) -> object:
        """Store ``batch``."""
        ...


def item(timestamp: float, value: float | None, good: bool = True) -> dict[str, Any]:
    """One ingest item; a bad or missing value is sent as ``value None, good False``."""
    if value is None or not good:
        return {"timestamp": timestamp, "value": None, "good": False}
    return {"timestamp": timestamp, "value": value, "good": True}


@dataclass(frozen=True)
class Backoff:
    """Capped exponential backoff with jitter (asyncua's reconnect pattern).

    Delays are ``initial * factor**k`` capped at ``maximum``, each multiplied
    by a random factor in ``[1 - jitter, 1]`` so that many clients do not
    reconnect in step.

    Examples
    --------
    >>> [round(d, 2) for d in Backoff(initial=0.5, maximum=4.0, jitter=0.0).delays(6)]
    [0.5, 1.0, 2.0, 4.0, 4.0, 4.0]
    """

    initial: float = 0.5
    maximum: float = 30.0
    factor: float = 2.0
    jitter: float = 0.1

    def delays(self, count: int | None = None, seed: int | None = None) -> Iterator[float]:
        """The successive waits (endless when ``count`` is None)."""
        rng = random.Random(seed)
        delay = self.initial
        k = 0
        while count is None or k < count:
            yield min(delay, self.maximum) * (1.0 - self.jitter * rng.random())
            delay *= self.factor
            k += 1
