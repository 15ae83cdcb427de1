"""Real servers for integration tests: a throw-away PostgreSQL cluster, and a TCP relay
on loopback that can cut the connections through it (a network outage while the server
behind it keeps running).

The cluster is created with ``initdb`` in a temporary directory and started
with ``pg_ctl`` on a free loopback port; under root (CI) both run as the
``postgres`` user, since PostgreSQL refuses to run as root.  Without
PostgreSQL installed the tests that need it skip with the reason, except
under ``LOOPWATCH_REQUIRE_ALL=1`` where they fail.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

PG_BIN_DIRS = sorted(Path("/usr/lib/postgresql").glob("*/bin"), reverse=True)


def require(condition: bool, reason: str) -> None:
    """Skip (or fail under LOOPWATCH_REQUIRE_ALL=1) unless ``condition``."""
    if condition:
        return
    if os.environ.get("LOOPWATCH_REQUIRE_ALL") == "1":
        pytest.fail(f"{reason} (LOOPWATCH_REQUIRE_ALL=1)")
    pytest.skip(reason)


def free_port() -> int:
    """A free TCP port on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class TcpRelay:
    """Relays loopback connections on :attr:`port` to ``target_port``; :meth:`cut` drops
    them all and refuses new ones until :meth:`restore`."""

    def __init__(self, target_port: int) -> None:
        self.target_port = target_port
        self.port = 0
        self.open = True
        self._server: asyncio.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()

    async def __aenter__(self) -> TcpRelay:
        self._server = await asyncio.start_server(self._relay, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        self.cut()
        assert self._server is not None
        self._server.close()
        await self._server.wait_closed()

    def cut(self) -> None:
        """Close every relayed connection; refuse new ones."""
        self.open = False
        for writer in list(self._writers):
            writer.transport.abort()
        self._writers.clear()

    def restore(self) -> None:
        """Relay new connections again."""
        self.open = True

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if not self.open:
            writer.transport.abort()
            return
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target_port)
        except OSError:
            writer.transport.abort()
            return
        self._writers |= {writer, up_writer}
        await asyncio.gather(self._pipe(reader, up_writer), self._pipe(up_reader, writer))

    async def _pipe(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(OSError, asyncio.IncompleteReadError):
            while data := await reader.read(65536):
                writer.write(data)
                await writer.drain()
        writer.transport.abort()
        self._writers.discard(writer)


def _pg_tool(name: str) -> str | None:
    for directory in PG_BIN_DIRS:
        if (directory / name).is_file():
            return str(directory / name)
    return shutil.which(name)


@contextmanager
def postgres_server() -> Iterator[str]:
    """Start a PostgreSQL cluster on a free loopback port; yield its SQLAlchemy URL."""
    initdb, pg_ctl = _pg_tool("initdb"), _pg_tool("pg_ctl")
    require(
        initdb is not None and pg_ctl is not None,
        "PostgreSQL server binaries (initdb, pg_ctl) not installed",
    )
    assert initdb is not None and pg_ctl is not None
    as_root = os.geteuid() == 0
    prefix = ["runuser", "-u", "postgres", "--"] if as_root else []
    base = Path(tempfile.mkdtemp(prefix="loopwatch-pg-"))
    data = base / "data"
    if as_root:
        shutil.chown(base, "postgres")
    port = free_port()
    try:
        subprocess.run(
            [*prefix, initdb, "-D", str(data), "-U", "loopwatch", "--auth=trust", "-E", "UTF8"],
            check=True, capture_output=True,
        )
        subprocess.run(
            [*prefix, pg_ctl, "-D", str(data), "-l", str(base / "log"), "-w", "start", "-o",
             f"-h 127.0.0.1 -p {port} -k {base} -F -c fsync=off -c full_page_writes=off"],
            check=True, capture_output=True,
        )
        yield f"postgresql+psycopg://loopwatch@127.0.0.1:{port}/postgres"
    finally:
        if (data / "postmaster.pid").exists():
            subprocess.run(
                [*prefix, pg_ctl, "-D", str(data), "-m", "immediate", "stop"],
                capture_output=True,
            )
        shutil.rmtree(base, ignore_errors=True)
