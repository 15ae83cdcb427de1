"""Type aliases every module shares: numpy arrays and the process type.

Written once here (the analytics modules and the service import them), so a
grep for ``ProcessType`` finds the one definition.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray

__all__ = ["INTEGRATING", "SELF_REGULATING", "BoolArray", "ComplexArray", "FloatArray",
           "IntArray", "ProcessType"]

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]

ProcessType = Literal["self-regulating", "integrating"]
"""How the process answers a valve step: it settles (flow, pressure, temperature) or
it integrates (level)."""
SELF_REGULATING: ProcessType = "self-regulating"
INTEGRATING: ProcessType = "integrating"
