"""Access to the real loop data in ../shared/data for tests.

Tests skip with the reason when the data are absent, except under
``LOOPWATCH_REQUIRE_ALL=1`` (CI), where a missing data set fails the test.
"""

import csv
import os
from pathlib import Path

import numpy as np
import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
ISDB = Path(os.environ.get("LOOPWATCH_ISDB14", SHARED_DATA / "isdb14"))


def require_file(path: Path) -> Path:
    """``path`` if it exists; otherwise skip (or fail under LOOPWATCH_REQUIRE_ALL=1)."""
    if path.is_file():
        return path
    reason = f"shared data not found at {path} (is ../shared beside the repository?)"
    if os.environ.get("LOOPWATCH_REQUIRE_ALL") == "1":
        pytest.fail(reason)
    pytest.skip(reason)


def load_isdb_loop(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """t_s, OP, PV of one ISDB loop (Jelali & Huang 2010)."""
    table = np.genfromtxt(require_file(ISDB / f"{name}.csv"), delimiter=",", names=True)
    return table["t_s"], table["OP"], table["PV"]


def isdb_labels() -> list[dict[str, str]]:
    """Rows of isdb14/labels.csv: loop, label, oscillating, ts_s, process_type_note."""
    with require_file(ISDB / "labels.csv").open(newline="") as handle:
        return list(csv.DictReader(handle))


OSC_DEV = Path(os.environ.get("LOOPWATCH_OSC_DEV", SHARED_DATA / "osc_dev"))


def osc_dev_labels() -> list[dict[str, str]]:
    """Rows of osc_dev/labels.csv: loop, oscillating (0/1), ts_s (Jelali & Huang 2010)."""
    with require_file(OSC_DEV / "labels.csv").open(newline="") as handle:
        return list(csv.DictReader(handle))


def load_osc_dev_loop(name: str) -> np.ndarray:
    """OP of one osc_dev loop (the files hold ``time,op``)."""
    table = np.genfromtxt(require_file(OSC_DEV / f"{name}.csv"), delimiter=",", names=True)
    return np.asarray(table["op"], dtype=np.float64)
