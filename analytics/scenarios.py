"""Named simulation scenarios: the thesis examples and a few typical plant loops.

Each factory returns a :class:`analytics.simulation.ClosedLoopModel`; the
:data:`SCENARIOS` registry maps a name to its factory and description for
``loopwatch simulate``.

References
----------
.. [1] Thesis chapter 4 (Eqs. before Fig. 4.7): G = 0.66 e^-2.6s/(6.7s+1),
   Gc = 0.1 + 0.09/s, He valve fs = 3, fd = 2, SP = 2.
.. [2] Thesis Eq. 2.10 (the ethanol-water column of ref. [31]), tunings
   Eqs. 2.11-2.13 (= Eq. 3.25) and Eq. 3.26, valves of Table 2.3.
.. [3] Thesis section 5.5.1: the temperature loop G = 0.4346 e^-6s/(27.58s+1).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from analytics.errors import ModelSpecError
from analytics.lti import TransferFunction
from analytics.simulation import ClosedLoopModel, Disturbance, Loop, PIDController
from analytics.valves import ChoudhuryValve, HeValve, IdealValve, KanoValve, ValveModel

UNLIMITED = (-math.inf, math.inf)

COLUMN_PROCESS = (
    (
        TransferFunction.fopdt(0.66, 6.7, 2.6),
        TransferFunction.fopdt(-0.61, 8.64, 3.5),
        TransferFunction.fopdt(-0.0049, 9.06, 1.0),
    ),
    (
        TransferFunction.fopdt(1.11, 3.25, 6.5),
        TransferFunction.fopdt(-2.36, 5.0, 3.0),
        TransferFunction.fopdt(-0.012, 7.09, 1.2),
    ),
    (
        TransferFunction.fopdt(-33.68, 8.15, 9.2),
        TransferFunction.fopdt(46.2, 10.9, 9.4),
        TransferFunction.lead_lag(0.87, 11.61, 3.89, 18.8, 1.0),
    ),
)
"""Thesis Eq. 2.10: entry (i, j) from valve j to PV i."""

COLUMN_TUNINGS = {
    "2.11": ((0.65, 0.09), (-0.157, -0.031), (0.675, 0.61)),  # Eqs. 2.11-2.13 = Eq. 3.25
    "3.26": ((2.0, 0.05), (-1.0, -0.031), (2.0, 0.61)),
}
"""(Kp, Ki) per loop."""

COLUMN_VALVES = (HeValve(4.5, 1.5), HeValve(3.0, 1.0), HeValve(4.0, 1.0))
"""Thesis Table 2.3 (He model) for valves 1, 2 and 3."""


def chapter4(*, sticky: bool = True) -> ClosedLoopModel:
    """The single loop of thesis chapter 4 [1], with or without its sticky valve.

    Sampled at 1 s. With He's model the period of the limit cycle depends on
    where the valve comes to rest within its last slip: at 0.1 s sampling the
    valve happens to stop within 0.01 % of equilibrium and the cycle stretches
    to thousands of seconds, so the coarser DCS-like scan is used here.
    """
    loop = Loop(
        controller=PIDController.parallel(0.1, 0.09),
        valve=HeValve(3.0, 2.0) if sticky else IdealValve(),
        setpoint=[(10.0, 52.0)],
        pv_bias=50.0,
        name="loop1",
    )
    return ClosedLoopModel(
        process=TransferFunction.fopdt(0.66, 6.7, 2.6), loops=(loop,), dt=1.0, duration=8000.0
    )


def column3x3(
    *,
    sticky: Sequence[int] = (1, 2, 3),
    tuning: str = "2.11",
    noise_std: float = 0.1,
    seed: int = 0,
    dt: float = 0.5,
    duration: float = 8000.0,
) -> ClosedLoopModel:
    """The 3x3 column of thesis Eq. 2.10 [2] with He valves of Table 2.3 in the
    loops listed in ``sticky`` (1-based).

    Signals are deviations from the operating point (no OP limits), as in the
    thesis; measurement noise of variance 0.01 (std 0.1) as in section 2.4; a
    setpoint step of +1 in every loop at 10 s starts the oscillation. Sampled
    at 0.5 s: fine against the smallest lag (3.25 s), and coarse enough that
    He's valves do not creep to rest in slips of ``fs - fd`` (see
    :func:`chapter4`). Tuning Eq. 3.26 is close to the linear stability
    limit: at 1 s sampling the loops diverge.
    """
    if tuning not in COLUMN_TUNINGS:
        raise ModelSpecError(
            f"unknown column tuning {tuning!r}; expected one of {sorted(COLUMN_TUNINGS)}"
        )
    bad = [i for i in sticky if i not in (1, 2, 3)]
    if bad:
        raise ModelSpecError(f"sticky valves are numbered 1-3, got {bad}")
    loops = []
    for i, (kp, ki) in enumerate(COLUMN_TUNINGS[tuning]):
        valve: ValveModel = COLUMN_VALVES[i] if i + 1 in sticky else IdealValve()
        loops.append(
            Loop(
                controller=PIDController.parallel(kp, ki, op_limits=UNLIMITED, op_bias=0.0),
                valve=valve,
                setpoint=[(10.0, 1.0)],
                pv_bias=0.0,
                disturbances=(Disturbance("noise", noise_std, at="measurement", seed=seed + i),),
                name=f"loop{i + 1}",
            )
        )
    return ClosedLoopModel(process=COLUMN_PROCESS, loops=tuple(loops), dt=dt, duration=duration)


def temperature_loop(*, tuning: str = "oscillating", noise_std: float = 0.0) -> ClosedLoopModel:
    """The temperature loop of thesis section 5.5.1 [3] with a Choudhury valve S = 4, J = 2.

    ``tuning="oscillating"``: Kc = 10, Ti = 10 s (the loop cycles);
    ``tuning="safe"``: Kc = 2, Ti = 100 s, the retune the thesis reports as removing
    the cycle; in this simulation a slow cycle (about 600 s) remains.
    """
    tunings = {"oscillating": (10.0, 10.0), "safe": (2.0, 100.0)}
    if tuning not in tunings:
        raise ModelSpecError(f"unknown tuning {tuning!r}; expected one of {sorted(tunings)}")
    kc, ti = tunings[tuning]
    valve: ValveModel = ChoudhuryValve(4.0, 2.0) if noise_std == 0 else KanoValve(4.0, 2.0)
    loop = Loop(
        controller=PIDController.ideal(kc, ti),
        valve=valve,
        setpoint=[(20.0, 51.0)],
        pv_bias=50.0,
        disturbances=(Disturbance("noise", noise_std, at="measurement", seed=5),)
        if noise_std
        else (),
        name="TIC",
    )
    return ClosedLoopModel(
        process=TransferFunction.fopdt(0.4346, 27.58, 6.0), loops=(loop,), dt=1.0, duration=8000.0
    )


def level_loop(*, sticky: bool = True) -> ClosedLoopModel:
    """A level loop (integrating process K = 0.02 %/s per %, 3 s dead time) under PI
    control with a Kano valve S = 3, J = 1 and sensor noise: stiction on an
    integrating process gives a triangular PV and a square-ish OP (thesis Table 2.2)."""
    loop = Loop(
        controller=PIDController.ideal(2.0, 200.0),
        valve=KanoValve(3.0, 1.0) if sticky else IdealValve(),
        setpoint=[(20.0, 55.0)],
        pv_bias=50.0,
        disturbances=(Disturbance("noise", 0.05, at="measurement", seed=7),),
        name="LIC",
    )
    return ClosedLoopModel(
        process=TransferFunction.integrating(0.02, 3.0), loops=(loop,), dt=1.0, duration=6000.0
    )


@dataclass(frozen=True)
class Scenario:
    """A named scenario for the CLI."""

    description: str
    build: Callable[[], ClosedLoopModel]


SCENARIOS: dict[str, Scenario] = {
    "chapter4": Scenario("thesis ch. 4 loop, He valve fs=3 fd=2 (oscillates)", chapter4),
    "chapter4-healthy": Scenario(
        "thesis ch. 4 loop, healthy valve (settles)", lambda: chapter4(sticky=False)
    ),
    "column-1": Scenario("3x3 column (Eq. 2.10), valve 1 sticky", lambda: column3x3(sticky=(1,))),
    "column-2": Scenario("3x3 column, valves 1 and 2 sticky", lambda: column3x3(sticky=(1, 2))),
    "column-3": Scenario("3x3 column, all three valves sticky (Table 2.3)", column3x3),
    "column-tuning-3.25": Scenario(
        "3x3 column, valves 2 and 3 sticky, tuning Eq. 3.25",
        lambda: column3x3(sticky=(2, 3), tuning="2.11"),
    ),
    "column-tuning-3.26": Scenario(
        "3x3 column, valves 2 and 3 sticky, tuning Eq. 3.26",
        lambda: column3x3(sticky=(2, 3), tuning="3.26"),
    ),
    "temperature": Scenario(
        "thesis 5.5.1 temperature loop, Kc=10 Ti=10 (oscillates)", temperature_loop
    ),
    "temperature-safe": Scenario(
        "thesis 5.5.1 temperature loop retuned to Kc=2 Ti=100",
        lambda: temperature_loop(tuning="safe"),
    ),
    "level": Scenario("integrating level loop with a sticky valve", level_loop),
    "level-healthy": Scenario(
        "integrating level loop, healthy valve", lambda: level_loop(sticky=False)
    ),
}


def build_scenario(name: str) -> ClosedLoopModel:
    """The model of scenario ``name``; unknown names list the known ones."""
    try:
        return SCENARIOS[name].build()
    except KeyError:
        raise ModelSpecError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}") from None
