"""What the tests of analytics.model_check share: a base loop model and OP series."""

import numpy as np

from analytics.model_check import LoopModel

BASE = {
    "dt": 1.0,
    "op_bias": 45.0,
    "process": {"type": "fopdt", "K": 1.5, "tau": 12.0, "theta": 3.0},
    "controller": {"type": "PI", "Kc": 0.5, "Ti": 10.0},
    "valve": {"model": "he", "fs": 3.0, "fd": 1.0},
}


def model_with(**changes: object) -> LoopModel:
    return LoopModel.from_dict({**BASE, **changes})


def slow_ramp(low: float, high: float, step: float = 0.01) -> np.ndarray:
    up = np.arange(low, high, step)
    return np.concatenate([up, up[::-1]])


FRICTIONS = np.array([[3.0, 1.0], [1.2, 0.2]])
"""Two frictions in a valve model's own parameters (He's fs, fd; S, J of the band models)."""


def friction_model(name: str) -> LoopModel:
    keys = ("fs", "fd") if name == "he" else ("S", "J")
    return model_with(valve={"model": name, **dict(zip(keys, FRICTIONS[0], strict=True))})


def walk(n: int = 3000, seed: int = 3) -> np.ndarray:
    return 50.0 + np.cumsum(np.random.default_rng(seed).normal(0.0, 0.8, n))

