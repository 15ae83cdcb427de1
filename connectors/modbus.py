"""Modbus TCP polling: register codecs, the connector configuration and the connector.

A Modbus device exposes 16-bit registers; a tag is one value spread over one
(int16, uint16) or two (int32, uint32, float32) consecutive registers.  How
the bytes of the value are laid out is the device's choice, named after the
bytes ``A B C D`` of the big-endian value (A the most significant):

========  =========================  ========================================
order     registers of 0x42F6E979    meaning
========  =========================  ========================================
ABCD      [0x42F6, 0xE979]           big-endian words, big-endian bytes
CDAB      [0xE979, 0x42F6]           words swapped (the common "word swap")
BADC      [0xF642, 0x79E9]           bytes swapped inside each word
DCBA      [0x79E9, 0xF642]           fully little-endian
========  =========================  ========================================

For one-register types only the byte swap matters: BADC and DCBA store
``AB`` as ``BA``.  Raw values can be scaled linearly from a raw range to
engineering units; a raw value outside its raw range, or not finite, is sent
as a bad sample.

The connector polls its groups one request at a time over one connection,
stamps every value at the poll, and hands the batches to a
:class:`~connectors.base.SampleSink` in a worker thread.  When the connection
drops or a request times out it closes the connection, records an
:class:`~connectors.base.Outage`, and reconnects with capped exponential
backoff; nothing is stored while the connection is down, so the window shows
the gap.

References
----------
Modbus Organization, *MODBUS Application Protocol Specification V1.1b3*
(2012), functions 0x03 (read holding registers) and 0x04 (read input
registers, at most 125 per request).
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from connectors.base import (
    BackgroundConnector,
    Backoff,
    DeliveryCounters,
    SampleSink,
    hand_over,
    item,
    raise_if_cancelled,
)

__all__ = [
    "REGISTER_COUNT",
    "DataType",
    "ModbusConnector",
    "ModbusConnectorConfig",
    "ModbusCounters",
    "ModbusGroupConfig",
    "ModbusTagConfig",
    "WordOrder",
    "decode",
    "encode",
    "to_engineering",
]

log = logging.getLogger(__name__)

DEFAULT_BACKOFF = Backoff()
"""Reconnection waits: 0.5 s doubling up to 30 s, with 10 % jitter."""

DataType = Literal["int16", "uint16", "int32", "uint32", "float32"]
WordOrder = Literal["ABCD", "CDAB", "BADC", "DCBA"]

REGISTER_COUNT: dict[DataType, int] = {
    "int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2,
}
"""Registers that one value of each data type occupies."""

_STRUCT_FORMAT: dict[DataType, str] = {
    "int16": ">h", "uint16": ">H", "int32": ">i", "uint32": ">I", "float32": ">f",
}
_INTEGER_RANGE: dict[DataType, tuple[int, int]] = {
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
}


_WORD_ORDERS = frozenset(get_args(WordOrder))


def _check_layout(data_type: str, word_order: str) -> None:
    if data_type not in REGISTER_COUNT:
        raise ValueError(
            f"unknown data type {data_type!r}; use one of {', '.join(get_args(DataType))}"
        )
    if word_order not in _WORD_ORDERS:
        raise ValueError(
            f"unknown word order {word_order!r}; use one of {', '.join(get_args(WordOrder))}"
        )


def _reorder(data: bytes, word_order: WordOrder) -> bytes:
    """Big-endian bytes to the device layout; applied twice it gives the bytes back."""
    if word_order in ("BADC", "DCBA"):
        data = b"".join(data[i : i + 2][::-1] for i in range(0, len(data), 2))
    if word_order in ("CDAB", "DCBA"):
        data = b"".join(data[i : i + 2] for i in reversed(range(0, len(data), 2)))
    return data


def encode(value: float, data_type: DataType, word_order: WordOrder = "ABCD") -> list[int]:
    """The registers that hold ``value`` as ``data_type`` in ``word_order``.

    Raises
    ------
    ValueError
        Unknown type or order, an integer type given a fraction, NaN or a value
        out of its range, or a float32 value beyond the float32 range.

    Examples
    --------
    >>> [hex(r) for r in encode(123.456, "float32", "CDAB")]
    ['0xe979', '0x42f6']
    >>> encode(-2, "int16", "ABCD"), encode(-2, "int16", "BADC")
    ([65534], [65279])
    """
    _check_layout(data_type, word_order)
    if data_type == "float32":
        try:
            packed = struct.pack(">f", value)
        except OverflowError:
            raise ValueError(f"{value!r} is outside the float32 range") from None
    else:
        low, high = _INTEGER_RANGE[data_type]
        if not (math.isfinite(value) and float(value).is_integer()):
            raise ValueError(f"{data_type} holds whole numbers only, got {value!r}")
        if not low <= value <= high:
            raise ValueError(f"{value!r} is outside the {data_type} range [{low}, {high}]")
        packed = struct.pack(_STRUCT_FORMAT[data_type], int(value))
    data = _reorder(packed, word_order)
    return [int.from_bytes(data[i : i + 2], "big") for i in range(0, len(data), 2)]


def decode(registers: list[int], data_type: DataType, word_order: WordOrder = "ABCD") -> float:
    """The value that ``registers`` hold as ``data_type`` in ``word_order``.

    Raises
    ------
    ValueError
        Unknown type or order, the wrong number of registers, or a register
        outside 0..65535.

    Examples
    --------
    >>> round(decode([0x79E9, 0xF642], "float32", "DCBA"), 3)
    123.456
    >>> decode([0xFFFF, 0xFFFE], "int32", "ABCD"), decode([0xFFFF, 0xFFFE], "uint32", "ABCD")
    (-2.0, 4294967294.0)
    """
    _check_layout(data_type, word_order)
    if len(registers) != REGISTER_COUNT[data_type]:
        raise ValueError(
            f"{data_type} takes {REGISTER_COUNT[data_type]} register(s), got {len(registers)}"
        )
    for register in registers:
        if not 0 <= register <= 0xFFFF:
            raise ValueError(f"register value {register} is outside 0..65535")
    data = _reorder(b"".join(r.to_bytes(2, "big") for r in registers), word_order)
    return float(struct.unpack(_STRUCT_FORMAT[data_type], data)[0])


def to_engineering(
    raw: float, raw_range: tuple[float, float], eng_range: tuple[float, float]
) -> float:
    """Scale ``raw`` linearly so that ``raw_range`` maps onto ``eng_range``.

    Examples
    --------
    >>> to_engineering(6400, (0, 32000), (0.0, 250.0))  # a 0..32000 analogue input card
    50.0
    """
    (raw_low, raw_high), (eng_low, eng_high) = raw_range, eng_range
    return eng_low + (raw - raw_low) * (eng_high - eng_low) / (raw_high - raw_low)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ModbusTagConfig(_Strict):
    """One tag of a polling group: where its registers are and how to read them."""

    tag: str = Field(min_length=1)
    offset: int = Field(ge=0, description="first register, counted from the group's start")
    data_type: DataType = "float32"
    word_order: WordOrder = "ABCD"
    raw_range: tuple[float, float] | None = Field(
        default=None, description="valid raw values; outside them a sample is bad"
    )
    eng_range: tuple[float, float] | None = Field(
        default=None, description="engineering values that raw_range maps onto"
    )

    @field_validator("raw_range")
    @classmethod
    def _raw_increasing(cls, raw_range: tuple[float, float] | None) -> tuple[float, float] | None:
        if raw_range is not None and not raw_range[1] > raw_range[0]:
            raise ValueError(f"raw_range must have high > low, got {list(raw_range)}")
        return raw_range

    @model_validator(mode="after")
    def _scaling_needs_raw_range(self) -> ModbusTagConfig:
        if self.eng_range is not None:
            if self.raw_range is None:
                raise ValueError("eng_range needs raw_range (the raw values it maps from)")
            if self.eng_range[0] == self.eng_range[1]:
                raise ValueError(f"eng_range must span something, got {list(self.eng_range)}")
        return self

    @property
    def registers(self) -> int:
        """Registers the tag occupies."""
        return REGISTER_COUNT[self.data_type]


class ModbusGroupConfig(_Strict):
    """Registers read in one request, and the tags inside them."""

    function: Literal["holding", "input"] = "holding"
    start: int = Field(ge=0, le=0xFFFF, description="first register address (0-based)")
    count: int = Field(ge=1, le=125, description="registers per request (Modbus allows 125)")
    tags: list[ModbusTagConfig] = Field(min_length=1)

    @model_validator(mode="after")
    def _tags_fit_without_overlap(self) -> ModbusGroupConfig:
        if self.start + self.count > 0x10000:
            raise ValueError(
                f"start {self.start} + count {self.count} runs past register 65535"
            )
        placed = sorted(enumerate(self.tags), key=lambda pair: pair[1].offset)
        for (i, tag), (j, later) in itertools.pairwise(placed):
            if later.offset < tag.offset + tag.registers:
                raise ValueError(
                    f"tags[{j}] ({later.tag!r}, offset {later.offset}) overlaps tags[{i}] "
                    f"({tag.tag!r}, {tag.data_type} at offsets {tag.offset}.."
                    f"{tag.offset + tag.registers - 1})"
                )
        for i, tag in enumerate(self.tags):
            if tag.offset + tag.registers > self.count:
                raise ValueError(
                    f"tags[{i}] ({tag.tag!r}): {tag.data_type} at offset {tag.offset} needs "
                    f"offsets {tag.offset}..{tag.offset + tag.registers - 1}, but the group "
                    f"has count {self.count} (offsets 0..{self.count - 1})"
                )
        return self


class ModbusConnectorConfig(_Strict):
    """One Modbus TCP device (one connection) and the register groups polled from it.

    Examples
    --------
    >>> config = ModbusConnectorConfig.model_validate({
    ...     "host": "127.0.0.1", "port": 5020, "poll_interval_s": 1.0,
    ...     "groups": [{"function": "holding", "start": 0, "count": 4, "tags": [
    ...         {"tag": "FIC-101.PV", "offset": 0, "data_type": "float32"},
    ...         {"tag": "FIC-101.OP", "offset": 2, "data_type": "int16",
    ...          "raw_range": [0, 32000], "eng_range": [0, 100]}]}]})
    >>> [tag.tag for tag in config.tags()]
    ['FIC-101.PV', 'FIC-101.OP']
    """

    host: str = Field(min_length=1)
    port: int = Field(default=502, ge=1, le=65535)
    unit_id: int = Field(default=1, ge=0, le=255, description="Modbus unit (device) id")
    poll_interval_s: float = Field(default=1.0, gt=0)
    timeout_s: float = Field(default=3.0, gt=0, description="connect and answer timeout")
    groups: list[ModbusGroupConfig] = Field(min_length=1)

    @model_validator(mode="after")
    def _tags_unique(self) -> ModbusConnectorConfig:
        seen: dict[str, str] = {}
        for g, group in enumerate(self.groups):
            for t, tag in enumerate(group.tags):
                where = f"groups[{g}].tags[{t}]"
                if tag.tag in seen:
                    raise ValueError(f"{where}: tag {tag.tag!r} is already read by {seen[tag.tag]}")
                seen[tag.tag] = where
        return self

    def tags(self) -> Iterator[ModbusTagConfig]:
        """Every tag, group by group."""
        for group in self.groups:
            yield from group.tags


@dataclass
class ModbusCounters(DeliveryCounters):
    """What a :class:`ModbusConnector` has done, besides the sample counts of its base class.

    Attributes
    ----------
    polls : int
        Requests answered, exception responses included.
    error_responses : int
        Modbus exception responses; the tags of that group are sent as bad.
    registers_read : int
        Registers received.
    reconnects : int
        Connections made after the first.
    outages : int
        Times the connection was lost or could not be made (see ``Outage``).
    skipped_cycles : int
        Poll cycles left out because a cycle overran the poll interval.
    """

    polls: int = 0
    error_responses: int = 0
    registers_read: int = 0
    reconnects: int = 0
    outages: int = 0
    skipped_cycles: int = 0


class ModbusConnector(BackgroundConnector[ModbusCounters]):
    """Poll the groups of one Modbus TCP device and hand the samples to ``sink``.

    Each poll cycle reads every group, one request at a time, stamps each
    group's values with the time its request was sent, and queues one batch
    for the sink; a worker thread (``asyncio.to_thread``) hands the queued
    batches over, merged, so a slow database never delays the polls.  A
    dropped connection or an unanswered request closes the connection,
    opens an :class:`~connectors.base.Outage` and reconnects after the waits
    of ``backoff``.

    Use ``await connector.run()`` (until cancelled) inside an event loop, or
    :meth:`start` / :meth:`stop` to run it in a thread of its own.

    Examples
    --------
    >>> config = ModbusConnectorConfig(host="127.0.0.1", port=5020, groups=[
    ...     ModbusGroupConfig(start=0, count=2, tags=[ModbusTagConfig(tag="T", offset=0)])])
    >>> connector = ModbusConnector(config, print)
    >>> connector.counters.polls, connector.outages
    (0, [])
    """

    def __init__(
        self, config: ModbusConnectorConfig, sink: SampleSink, *, backoff: Backoff = DEFAULT_BACKOFF
    ) -> None:
        super().__init__(f"modbus {config.host}:{config.port}", ModbusCounters())
        self.config = config
        self._sink = sink
        self._backoff = backoff
        self._failing_groups: set[int] = set()

    async def run(self) -> None:
        """Poll until cancelled, reconnecting after every loss."""
        queue: asyncio.Queue[list[dict[str, Any]] | None] = asyncio.Queue()
        deliverer = asyncio.create_task(self._deliver(queue))
        try:
            await self._supervise(queue)
        finally:
            queue.put_nowait(None)
            await deliverer

    async def _supervise(self, queue: asyncio.Queue[list[dict[str, Any]] | None]) -> None:
        """Connect, poll until the connection fails, wait, reconnect: until cancelled."""
        host, port = self.config.host, self.config.port
        delays = self._backoff.delays()
        connected_before = False
        while True:
            client = AsyncModbusTcpClient(
                host, port=port, timeout=self.config.timeout_s, retries=0, reconnect_delay=0,
                name=self.name,
            )
            try:
                if await client.connect():
                    if connected_before:
                        with self._counters.lock:
                            self._counters.reconnects += 1
                    connected_before = True
                    self._outages.restored()
                    delays = self._backoff.delays()
                    log.info("%s: connected", self.name)
                    reason = await self._poll(client, queue)
                else:
                    reason = f"cannot connect to {host}:{port}"
            except Exception as exc:
                log.exception("%s: unexpected error while polling", self.name)
                reason = f"unexpected error: {exc!r}"
            finally:
                client.close()
            raise_if_cancelled()
            if self._outages.lost(reason):
                with self._counters.lock:
                    self._counters.outages += 1
            await asyncio.sleep(next(delays))

    async def _poll(
        self, client: AsyncModbusTcpClient, queue: asyncio.Queue[list[dict[str, Any]] | None]
    ) -> str:
        """Poll every group each interval until the connection fails; the reason it did.

        A stop cancels the task; a cancellation that comes as a response does can be
        lost inside the read, so each read first checks that none is pending
        (:func:`~connectors.base.raise_if_cancelled`).
        """
        loop = asyncio.get_running_loop()
        interval = self.config.poll_interval_s
        next_cycle = loop.time()
        while True:
            batch: list[dict[str, Any]] = []
            try:
                for index, group in enumerate(self.config.groups):
                    raise_if_cancelled()
                    if not client.connected:
                        return "the connection was closed"
                    read = (
                        client.read_holding_registers
                        if group.function == "holding"
                        else client.read_input_registers
                    )
                    stamp = time.time()
                    try:
                        response = await read(
                            group.start, count=group.count, device_id=self.config.unit_id
                        )
                    except ModbusIOException as exc:
                        return f"no answer within {self.config.timeout_s} s: {exc}"
                    except (ConnectionException, ModbusException) as exc:
                        return f"the connection failed: {exc}"
                    batch.extend(self._samples(index, response, stamp))
            finally:  # what was read is delivered, also when the cycle is cut short
                if batch:
                    queue.put_nowait(batch)
            next_cycle += interval
            late = loop.time() - next_cycle
            if late > 0:
                skipped = math.ceil(late / interval)
                with self._counters.lock:
                    self._counters.skipped_cycles += skipped
                next_cycle += skipped * interval
            await asyncio.sleep(next_cycle - loop.time())

    def _samples(self, index: int, response: ModbusPDU, stamp: float) -> list[dict[str, Any]]:
        """The group's tags as ingest entries; all bad if the device answered with an error."""
        group = self.config.groups[index]
        registers = list(response.registers)
        failed = response.isError() or len(registers) < group.count
        if failed:
            if index not in self._failing_groups:
                log.warning(
                    "%s: groups[%d] (%s registers %d..%d) answered %s; its tags are sent as bad",
                    self.name, index, group.function, group.start,
                    group.start + group.count - 1, response,
                )
            self._failing_groups.add(index)
        else:
            self._failing_groups.discard(index)
        values = [None if failed else self._value(tag, registers) for tag in group.tags]
        with self._counters.lock:
            self._counters.polls += 1
            if failed:
                self._counters.error_responses += 1
            else:
                self._counters.registers_read += len(registers)
            self._counters.samples += len(values)
            self._counters.bad += values.count(None)
        return [{"tag": tag.tag, "items": [item(stamp, value)]}
                for tag, value in zip(group.tags, values, strict=True)]

    @staticmethod
    def _value(tag: ModbusTagConfig, registers: list[int]) -> float | None:
        """The tag's value in engineering units; None when not finite or out of raw range."""
        raw = decode(
            registers[tag.offset : tag.offset + tag.registers], tag.data_type, tag.word_order
        )
        if not math.isfinite(raw):
            return None
        if tag.raw_range is not None:
            if not tag.raw_range[0] <= raw <= tag.raw_range[1]:
                return None
            if tag.eng_range is not None:
                return to_engineering(raw, tag.raw_range, tag.eng_range)
        return raw

    async def _deliver(self, queue: asyncio.Queue[list[dict[str, Any]] | None]) -> None:
        """Hand queued batches to the sink in a worker thread until the end marker."""
        finished = False
        while not finished:
            entries = await queue.get()
            if entries is None:
                break
            while not queue.empty():
                more = queue.get_nowait()
                if more is None:
                    finished = True
                    break
                entries.extend(more)
            await self._hand_over(entries)

    async def _hand_over(self, entries: list[dict[str, Any]]) -> None:
        merged: dict[str, list[dict[str, Any]]] = {}
        for entry in entries:
            merged.setdefault(entry["tag"], []).extend(entry["items"])
        batch = [{"tag": tag, "items": items} for tag, items in merged.items()]
        await hand_over(self._sink, batch, self._counters, self.name)
