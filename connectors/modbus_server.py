"""A Modbus TCP server whose registers hold named tags: the plant simulator's Modbus side.

:class:`ModbusRegisterServer` serves a register image over pymodbus's async
TCP server.  Each tag of its address map occupies one or two registers at a
fixed address, in the data type and word order of the map (see
:mod:`connectors.modbus`); :meth:`~ModbusRegisterServer.set` writes a value,
:meth:`~ModbusRegisterServer.set_bad` writes float32 NaN, the way many
controllers report a failed measurement.  Holding-register (0x03) and
input-register (0x04) reads see the same image; clients cannot write.  For
fault tests, :meth:`~ModbusRegisterServer.drop_connections` aborts every
client connection, and ``stop()`` / ``start()`` take the server away and back
on the same port.
"""

from __future__ import annotations

import asyncio
import math
import threading
from collections.abc import Mapping

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType as SimDataType
from pymodbus.simulator import SimData, SimDevice

from connectors.modbus import REGISTER_COUNT, DataType, WordOrder, encode

__all__ = ["AddressMap", "ModbusRegisterServer"]

AddressMap = Mapping[str, tuple[int, DataType, WordOrder]]
"""tag -> (first register address, data type, word order)."""


class ModbusRegisterServer:
    """Serve the tags of ``address_map`` as registers on ``host:port``.

    Parameters
    ----------
    host, port : str, int
        Where to listen; port 0 lets the system choose (read :attr:`port`
        after :meth:`start`).
    address_map : mapping
        tag -> (address, data type, word order); the registers of two tags
        must not overlap.  Every register starts at 0.

    Examples
    --------
    >>> server = ModbusRegisterServer("127.0.0.1", 0, {"FIC-101.PV": (0, "float32", "ABCD")})
    >>> server.set("FIC-101.PV", 123.456)
    >>> [hex(r) for r in server.registers("FIC-101.PV")]
    ['0x42f6', '0xe979']
    """

    def __init__(self, host: str, port: int, address_map: AddressMap) -> None:
        if not address_map:
            raise ValueError("the address map is empty: give at least one tag")
        self.host = host
        self._requested_port = port
        self._port: int | None = None
        self.address_map = dict(address_map)
        taken: dict[int, str] = {}
        for tag, (address, data_type, word_order) in self.address_map.items():
            encode(0, data_type, word_order)  # refuses an unknown type or order
            last = address + REGISTER_COUNT[data_type] - 1
            if address < 0 or last > 0xFFFF:
                raise ValueError(f"tag {tag!r}: registers {address}..{last} are outside 0..65535")
            for register in range(address, last + 1):
                if register in taken:
                    raise ValueError(
                        f"tag {tag!r}: register {register} is already used by {taken[register]!r}"
                    )
                taken[register] = tag
        self._first = min(taken)
        self._image = [0] * (max(taken) - self._first + 1)
        self._lock = threading.Lock()
        self._server: ModbusTcpServer | None = None

    @property
    def port(self) -> int:
        """The port listened on (the chosen one when constructed with port 0)."""
        if self._port is None:
            raise RuntimeError("the server is not started")
        return self._port

    def set(self, tag: str, value: float) -> None:
        """Write ``value`` into the registers of ``tag`` (safe from any thread).

        Raises
        ------
        KeyError
            ``tag`` is not in the address map.
        ValueError
            ``value`` does not fit the tag's data type.
        """
        address, data_type, word_order = self._layout(tag)
        try:
            registers = encode(value, data_type, word_order)
        except ValueError as exc:
            raise ValueError(f"tag {tag!r}: {exc}") from None
        start = address - self._first
        with self._lock:
            self._image[start : start + len(registers)] = registers

    def set_bad(self, tag: str) -> None:
        """Mark ``tag`` as a failed measurement: float32 NaN (float32 tags only)."""
        _, data_type, _ = self._layout(tag)
        if data_type != "float32":
            raise ValueError(f"tag {tag!r} is {data_type}, which has no NaN to mark it bad")
        self.set(tag, math.nan)

    def registers(self, tag: str) -> list[int]:
        """The registers of ``tag`` as served now."""
        address, data_type, _ = self._layout(tag)
        start = address - self._first
        with self._lock:
            return self._image[start : start + REGISTER_COUNT[data_type]]

    def _layout(self, tag: str) -> tuple[int, DataType, WordOrder]:
        try:
            return self.address_map[tag]
        except KeyError:
            raise KeyError(f"tag {tag!r} is not in the address map") from None

    async def _serve_image(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        current_registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """pymodbus request hook: copy the requested registers of the image into the datastore."""
        start = address - start_address
        with self._lock:
            current_registers[start : start + count] = self._image[start : start + count]
        return None

    async def start(self) -> None:
        """Listen on ``host:port`` (a server stopped before starts again on the same port)."""
        if self._server is not None:
            raise RuntimeError("the server is already running")
        device = SimDevice(
            id=0,  # answers every unit id
            simdata=SimData(
                self._first, count=len(self._image), values=0,
                datatype=SimDataType.REGISTERS, readonly=True,
            ),
            action=self._serve_image,
        )
        port = self._port if self._port is not None else self._requested_port
        server = ModbusTcpServer(device, address=(self.host, port))
        await server.serve_forever(background=True)
        self._server = server
        self._port = int(server.transport.sockets[0].getsockname()[1])  # type: ignore[attr-defined]

    async def stop(self) -> None:
        """Close the listener and every client connection."""
        if self._server is not None:
            await self._server.shutdown()
            self._server = None

    async def drop_connections(self) -> int:
        """Abort every client connection (the listener stays up); the number dropped."""
        if self._server is None:
            return 0
        connections = list(self._server.active_connections.values())
        for connection in connections:
            connection.transport.abort()  # type: ignore[attr-defined]
        await asyncio.sleep(0)  # let the transports report the loss
        return len(connections)

    async def __aenter__(self) -> ModbusRegisterServer:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.stop()
