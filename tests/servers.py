"""Real servers for integration tests: a throw-away PostgreSQL cluster.

The cluster is created with ``initdb`` in a temporary directory and started
with ``pg_ctl`` on a free loopback port; under root (CI) both run as the
``postgres`` user, since PostgreSQL refuses to run as root.  Without
PostgreSQL installed the tests that need it skip with the reason, except
under ``LOOPWATCH_REQUIRE_ALL=1`` where they fail.
"""

from __future__ import annotations

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
