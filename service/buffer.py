"""Rolling buffers: each tag's recent samples in memory, and loop windows cut from them.

Every configured tag has a :class:`RingBuffer` holding at least its samples
within ``horizon_s`` of its newest one; bad samples are kept as NaN so a window
shows the hole.  :class:`LoopBuffers` holds the buffers of all loops, is
rebuilt from the store at start-up (a restart loses no window), takes the
samples each ingest stores, and cuts a loop's signals onto a common uniform
grid for the analyses.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from sqlalchemy import select
from sqlalchemy.orm import Session

from analytics.types import FloatArray
from service.config import LoopConfig, PlantConfig
from service.store.models import Sample

__all__ = ["CAPACITY_MARGIN", "LoopBuffers", "LoopWindowData", "RingBuffer"]


CAPACITY_MARGIN = 1.1
"""Slots per tag as a multiple of ``horizon_s / ts``, for jitter and late samples."""


class RingBuffer:
    """The samples of one tag, in time order, covering at least ``horizon_s``.

    Appending samples later than the newest one is O(1) per sample and
    overwrites the oldest slots once they are older than the horizon.  A
    sample earlier than the newest (a late arrival) or a full buffer whose
    oldest sample is still inside the horizon (a tag sampled faster than
    ``ts``) makes the buffer rebuild itself: sort, drop what is older than
    the horizon, and grow if needed.  Nothing inside the horizon is lost.
    """

    def __init__(self, *, horizon_s: float, ts: float) -> None:
        if not (math.isfinite(horizon_s) and horizon_s > 0 and math.isfinite(ts) and ts > 0):
            raise ValueError(f"horizon_s and ts must be positive, got {horizon_s} and {ts}")
        self.horizon_s = horizon_s
        self._t: FloatArray = np.empty(math.ceil(horizon_s / ts * CAPACITY_MARGIN) + 1)
        self._v: FloatArray = np.empty_like(self._t)
        self._head = 0  # slot of the oldest sample
        self._size = 0

    @property
    def capacity(self) -> int:
        """Number of slots."""
        return int(self._t.size)

    def __len__(self) -> int:
        return self._size

    @property
    def nbytes(self) -> int:
        """Memory of the time and value arrays, bytes."""
        return int(self._t.nbytes + self._v.nbytes)

    def clear(self) -> None:
        """Forget every sample (the capacity stays)."""
        self._head = self._size = 0

    def _slices(self) -> tuple[slice, slice]:
        """The occupied slots in time order: two slices, the second empty unless wrapped."""
        end = self._head + self._size
        if end <= self.capacity:
            return slice(self._head, end), slice(0, 0)
        return slice(self._head, self.capacity), slice(0, end - self.capacity)

    def samples(self) -> tuple[FloatArray, FloatArray]:
        """Copies of all times and values, in time order."""
        first, second = self._slices()
        return (
            np.concatenate([self._t[first], self._t[second]]),
            np.concatenate([self._v[first], self._v[second]]),
        )

    def between(self, start: float, stop: float) -> tuple[FloatArray, FloatArray]:
        """Copies of the times and values with ``start <= t <= stop``, in time order."""
        parts = []
        for part in self._slices():
            times = self._t[part]
            lo = int(np.searchsorted(times, start, side="left"))
            hi = int(np.searchsorted(times, stop, side="right"))
            parts.append(slice(part.start + lo, part.start + hi))
        return (
            np.concatenate([self._t[p] for p in parts]),
            np.concatenate([self._v[p] for p in parts]),
        )

    def append(self, times: ArrayLike, values: ArrayLike) -> None:
        """Add samples (NaN values for bad ones); a time already held takes the new value."""
        t = np.asarray(times, dtype=np.float64).ravel()
        v = np.asarray(values, dtype=np.float64).ravel()
        if t.shape != v.shape:
            raise ValueError(f"{t.size} times but {v.size} values")
        if not np.isfinite(t).all():
            raise ValueError("sample times must be finite")
        if t.size == 0:
            return
        in_order = bool(np.all(np.diff(t) > 0))
        if in_order and (self._size == 0 or t[0] > self._t[self._last]):
            overwritten = self._size + t.size - self.capacity
            if overwritten <= 0 or self._time_at(overwritten - 1, t) < t[-1] - self.horizon_s:
                self._write(t, v)
                return
        self._rebuild(t, v)

    @property
    def oldest_time(self) -> float | None:
        """Time of the oldest sample held, or None when empty."""
        return float(self._t[self._head]) if self._size else None

    @property
    def newest_time(self) -> float | None:
        """Time of the newest sample held, or None when empty."""
        return float(self._t[self._last]) if self._size else None

    @property
    def _last(self) -> int:
        return (self._head + self._size - 1) % self.capacity

    def _time_at(self, index: int, incoming: FloatArray) -> float:
        """Time of sample ``index`` (0 = oldest) of the held samples followed by ``incoming``."""
        if index < self._size:
            return float(self._t[(self._head + index) % self.capacity])
        return float(incoming[index - self._size])

    def _write(self, t: FloatArray, v: FloatArray) -> None:
        """Write samples later than the newest, overwriting the oldest when full."""
        if t.size > self.capacity:
            t, v = t[-self.capacity :], v[-self.capacity :]
        slots = (self._head + self._size + np.arange(t.size)) % self.capacity
        self._t[slots], self._v[slots] = t, v
        overflow = max(0, self._size + t.size - self.capacity)
        self._head = (self._head + overflow) % self.capacity
        self._size = min(self.capacity, self._size + t.size)

    def _rebuild(self, t: FloatArray, v: FloatArray) -> None:
        """Merge samples in any order, keep the horizon, grow if it does not fit."""
        held_t, held_v = self.samples()
        all_t, all_v = np.concatenate([held_t, t]), np.concatenate([held_v, v])
        order = np.argsort(all_t, kind="stable")
        all_t, all_v = all_t[order], all_v[order]
        last_of_time = np.append(all_t[1:] != all_t[:-1], True)  # the latest write wins
        keep = last_of_time & (all_t >= all_t[-1] - self.horizon_s)
        all_t, all_v = all_t[keep], all_v[keep]
        if all_t.size > self.capacity:
            self._t = np.empty(math.ceil(all_t.size * CAPACITY_MARGIN) + 1)
            self._v = np.empty_like(self._t)
        self._t[: all_t.size], self._v[: all_t.size] = all_t, all_v
        self._head, self._size = 0, int(all_t.size)


@dataclass(frozen=True)
class LoopWindowData:
    """One loop's signals on a common uniform grid; NaN where a tag had no good sample.

    ``t`` holds the grid times (UNIX s, spaced ``ts``); ``op``, ``pv``, ``sp``,
    ``mv`` and ``mode`` (the controller's raw mode values) are None for
    signals the loop does not have.
    """

    t: FloatArray
    op: FloatArray | None
    pv: FloatArray | None
    sp: FloatArray | None
    mv: FloatArray | None
    ts: float
    mode: FloatArray | None = None

    @property
    def signals(self) -> dict[str, FloatArray]:
        """The measured signals the loop has, by name, not its mode (for
        ``analytics.quality.assess_quality``)."""
        named = {"op": self.op, "pv": self.pv, "sp": self.sp, "mv": self.mv}
        return {name: x for name, x in named.items() if x is not None}


def _whole_steps(x: float, ts: float) -> int:
    """``floor(x / ts)``, counting an ``x`` a rounding error below a multiple of ts as on it."""
    k = round(x / ts)
    return k if k * ts <= x or math.isclose(k * ts, x, rel_tol=1e-12, abs_tol=1e-9) else k - 1


def _held_good(times: FloatArray, values: FloatArray, grid: FloatArray, ts: float) -> FloatArray:
    """Each grid point's latest good sample stamped up to ``ts / 2`` after it, else NaN.

    For a state such as the controller's mode, which holds until the next
    value (many historians and DCSs report it only when it changes).
    """
    good = ~np.isnan(values)
    times, values = times[good], values[good]
    latest = np.searchsorted(times, grid + ts / 2, side="right") - 1
    return np.where(latest >= 0, values[np.clip(latest, 0, None)], np.nan) if times.size \
        else np.full(grid.size, np.nan)


def _nearest_good(times: FloatArray, values: FloatArray, grid: FloatArray, ts: float) -> FloatArray:
    """Each grid point's nearest good sample within ``ts / 2`` (ties: the earlier), else NaN."""
    good = ~np.isnan(values)
    times, values = times[good], values[good]
    out = np.full(grid.size, np.nan)
    if times.size == 0:
        return out
    after = np.clip(np.searchsorted(times, grid), 0, times.size - 1)
    before = np.clip(after - 1, 0, None)
    nearest = np.where(
        np.abs(times[after] - grid) < np.abs(grid - times[before]), after, before
    )
    close = np.abs(times[nearest] - grid) <= ts / 2
    out[close] = values[nearest[close]]
    return out


class LoopBuffers:
    """The rolling buffers of every tag of every loop; safe to use from several threads."""

    def __init__(self, plant: PlantConfig, *, horizon_s: float) -> None:
        self.horizon_s = horizon_s
        self._loops: dict[str, LoopConfig] = {}
        self._buffers: dict[str, RingBuffer] = {}
        self._lock = threading.RLock()
        for loop in plant.loops:
            self.add_loop(loop)

    def add_loop(self, loop: LoopConfig) -> None:
        """Add a loop or replace its configuration; buffers of tags it keeps stay filled."""
        with self._lock:
            old = self._loops.get(loop.id)
            kept = {tag for _, tag in loop.tags.items()}
            for _, tag in old.tags.items() if old is not None else []:
                if tag not in kept:
                    del self._buffers[tag]
            for tag in kept - self._buffers.keys():
                self._buffers[tag] = RingBuffer(horizon_s=self.horizon_s, ts=loop.ts)
            self._loops[loop.id] = loop

    @classmethod
    def from_store(cls, session: Session, loops: Sequence[LoopConfig], *, since: float,
                   now: float) -> LoopBuffers:
        """Buffers of ``loops`` refilled with their stored samples from ``since`` to ``now``.

        A process that keeps no buffers (an API replica, ``--role api``) cuts
        its windows from these exactly as the scheduler cuts them from its own.
        """
        buffers = cls(PlantConfig(), horizon_s=now - since + max(loop.ts for loop in loops))
        for loop in loops:
            buffers.add_loop(loop)
        buffers.rebuild_from_store(session, now)
        return buffers

    def holds_samples(self, loop_id: str) -> bool:
        """Whether any tag of the loop has a sample in its buffer (False for an unknown loop)."""
        with self._lock:
            loop = self._loops.get(loop_id)
            return loop is not None and any(
                len(self._buffers[tag]) > 0 for _, tag in loop.tags.items())

    def history_start(self) -> float | None:
        """Time of the oldest sample held for any loop, or None when nothing is held."""
        with self._lock:
            times = [buffer.oldest_time for buffer in self._buffers.values()]
        return min((t for t in times if t is not None), default=None)

    def arrived_end(self, loop_ids: Iterable[str], now: float, grace_s: float) -> float:
        """The end of windows of ``loop_ids`` at ``now`` without samples not yet arrived.

        A connector or historian delivers a sample a moment after its time
        stamp, so the newest grid points of a window ending at ``now`` may
        have no sample yet: they are not missing data.  This is the time up
        to which every tag of the loops has delivered (the oldest of their
        newest samples) when that lies less than ``grace_s`` before ``now``;
        otherwise ``now``: a longer silence is a gap, for the data-quality
        screen to report.
        """
        with self._lock:
            newest = [self._buffers[tag].newest_time for loop_id in loop_ids
                      if loop_id in self._loops for _, tag in self._loops[loop_id].tags.items()]
        if not newest or any(t is None for t in newest):
            return now
        arrived = min(t for t in newest if t is not None)
        return arrived if now - grace_s < arrived < now else now

    @property
    def tags(self) -> frozenset[str]:
        """The tags that have a buffer."""
        with self._lock:
            return frozenset(self._buffers)

    def rebuild_from_store(self, session: Session, now: float) -> int:
        """Refill every buffer with its tag's stored samples since ``now - horizon_s``.

        Returns the number of samples loaded.
        """
        loaded = 0
        with self._lock:
            for tag, buffer in self._buffers.items():
                rows = session.execute(
                    select(Sample.time, Sample.value, Sample.good)
                    .where(Sample.tag == tag, Sample.time >= now - self.horizon_s)
                    .order_by(Sample.time)
                ).all()
                buffer.clear()
                if rows:
                    self.append(tag, *zip(*rows, strict=True))
                loaded += len(rows)
        return loaded

    def append(
        self,
        tag: str,
        times: ArrayLike,
        values: ArrayLike | Sequence[float | None],
        good: ArrayLike | None = None,
    ) -> None:
        """Add samples of ``tag`` (None values and ``good == False`` become NaN).

        Raises KeyError if no loop has the tag.
        """
        t = np.asarray(times, dtype=np.float64)
        v = np.asarray(values, dtype=np.float64)  # None -> NaN
        if good is not None:
            v = np.where(np.asarray(good, dtype=bool), v, np.nan)
        with self._lock:
            if tag not in self._buffers:
                raise KeyError(f"tag {tag!r} is not in any loop of the plant configuration")
            self._buffers[tag].append(t, v)

    def append_new(
        self, new_samples: Mapping[str, Sequence[tuple[float, float | None, bool]]]
    ) -> None:
        """Add an ingest's ``new_samples``; tags without a buffer are left to the store."""
        with self._lock:
            for tag, samples in new_samples.items():
                if tag in self._buffers and samples:
                    times, values, good = zip(*samples, strict=True)
                    self.append(tag, times, values, good)

    def window(self, loop_id: str, duration_s: float, now: float) -> LoopWindowData:
        """The loop's signals over the last ``duration_s`` on a grid of the loop's ``ts``.

        The grid ends at the last multiple of ``ts`` not after ``now`` (so
        successive windows share their points) and has ``floor(duration_s /
        ts)`` points.  Each point takes the tag's nearest good sample within
        ``ts / 2``, as historians and connectors stamp a loop's signals almost
        together; where there is none the point is NaN.

        Raises KeyError for an unknown loop and ValueError for a duration
        that is not positive or longer than the buffer horizon.
        """
        if not (0 < duration_s <= self.horizon_s):
            raise ValueError(
                f"window of {duration_s} s: must be positive and at most the buffer "
                f"horizon of {self.horizon_s} s"
            )
        with self._lock:
            if loop_id not in self._loops:
                raise KeyError(f"no loop {loop_id!r} in the buffers")
            loop = self._loops[loop_id]
            ts = loop.ts
            points = max(1, _whole_steps(duration_s, ts))
            end = _whole_steps(now, ts) * ts
            grid = end - ts * np.arange(points - 1, -1, -1, dtype=np.float64)
            signals = {
                signal: _nearest_good(
                    *self._buffers[tag].between(grid[0] - ts / 2, grid[-1] + ts / 2), grid, ts
                )
                for signal, tag in loop.tags.items() if signal != "mode"
            }
            mode = None if loop.tags.mode is None else _held_good(
                *self._buffers[loop.tags.mode].between(-math.inf, grid[-1] + ts / 2), grid, ts)
        return LoopWindowData(
            t=grid,
            op=signals.get("op"),
            pv=signals.get("pv"),
            sp=signals.get("sp"),
            mv=signals.get("mv"),
            ts=ts,
            mode=mode,
        )

    def memory_bytes(self, loop_id: str) -> int:
        """Memory of the loop's buffers, bytes (for the scale-out benchmark)."""
        with self._lock:
            return sum(self._buffers[tag].nbytes for _, tag in self._loops[loop_id].tags.items())
