"""A labelled library of simulated loops for scoring stiction detection.

Each :class:`SyntheticCase` is a closed loop (:mod:`analytics.simulation`)
whose cause of oscillation is known by construction: a sticky valve (He or
Kano model, several sizes) or one of the causes that a detector must not
blame on the valve -- an external oscillating disturbance, aggressive tuning
with a healthy valve, or plain noise with no oscillation at all.  The cases
cover self-regulating (fast flow-like and slow temperature-like) and
integrating (level-like) processes, several sampling intervals and noise
levels, so a detector tuned on one corner cannot look good on all of them.

The ground truth of the stiction cases (S and J in % of OP span, the He
parametrisation ``fs``/``fd``) scores quantification as well.

Examples
--------
>>> cases = synthetic_library()
>>> sorted({c.label for c in cases})
['no_stiction', 'stiction']
>>> case = next(c for c in cases if c.name == "flow-he-S4-J2-ts0.5")
>>> case.S, case.J, case.process_type
(4.0, 2.0, 'self-regulating')
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from analytics.lti import TransferFunction
from analytics.simulation import Disturbance, Loop, PIDController, SimulationResult, simulate
from analytics.valves import HeValve, IdealValve, KanoValve, ValveModel

__all__ = ["PROCESSES", "SyntheticCase", "synthetic_library"]

Label = Literal["stiction", "no_stiction"]
ProcessKind = Literal["self-regulating", "integrating"]


@dataclass(frozen=True)
class _Process:
    """A process with a PI tuning that is well damped with a healthy valve."""

    model: TransferFunction
    kind: ProcessKind
    Kc: float
    Ti: float
    aggressive_Kc: float  # PI tuning with a gain margin of about 1.35
    aggressive_Ti: float
    sampling: tuple[float, float]  # sampling intervals (s) of the cases
    disturbance_periods: tuple[float, float, float]  # external sine periods (s)
    noise_levels: tuple[float, float]  # PV measurement noise std of the stiction cases


PROCESSES: dict[str, _Process] = {
    # flow-like: fast, small dead time
    "flow": _Process(
        TransferFunction.fopdt(1.2, 8.0, 2.0), "self-regulating",
        0.5, 8.0, 3.0, 4.0, (0.5, 1.0), (20.0, 60.0, 150.0), (0.05, 0.2),
    ),
    # temperature-like: slow, large dead time
    "temp": _Process(
        TransferFunction.fopdt(0.8, 60.0, 12.0), "self-regulating",
        1.5, 60.0, 6.5, 30.0, (2.0, 4.0), (200.0, 500.0, 1000.0), (0.05, 0.2),
    ),
    # level-like: integrating
    "level": _Process(
        TransferFunction.integrating(0.02, 4.0), "integrating",
        3.0, 300.0, 14.0, 100.0, (1.0, 2.0), (100.0, 300.0, 800.0), (0.02, 0.08),
    ),
}
"""Processes of the library: a sound PI tuning (gain margin 6-10), an aggressive
one (gain margin 1.35-1.5, phase margin 15-25 deg), sampling intervals, the
periods of the external disturbances and the sensor noise levels (the level
loop's high gain would turn larger noise into random slips instead of a cycle)."""


@dataclass(frozen=True)
class SyntheticCase:
    """One labelled simulated loop.

    Attributes
    ----------
    name : str
        Unique name, e.g. ``"flow-he-S4-J2-ts1"``.
    label : {"stiction", "no_stiction"}
        Ground truth.
    cause : str
        ``"stiction"``, ``"external_disturbance"``, ``"aggressive_tuning"`` or
        ``"noise"`` (no oscillation).
    process_type : {"self-regulating", "integrating"}
    ts : float
        Sampling interval in seconds.
    S, J : float or None
        True stick band and slip jump in % of OP span (None without
        stiction).
    valve : ValveModel
    """

    name: str
    label: Label
    cause: str
    process_type: ProcessKind
    ts: float
    S: float | None
    J: float | None
    valve: ValveModel
    process: TransferFunction
    controller: PIDController
    disturbances: tuple[Disturbance, ...]
    samples: int

    def simulate(self, warm_up: float = 0.2) -> SimulationResult:
        """Simulate the loop and drop the first ``warm_up`` fraction (start-up transient)."""
        n_total = round(self.samples / (1.0 - warm_up))
        loop = Loop(
            self.controller,
            self.valve,
            setpoint=[(5.0 * self.ts, 51.0)],
            pv_bias=50.0,
            disturbances=self.disturbances,
            name=self.name,
        )
        res = simulate(self.process, loop, dt=self.ts, duration=n_total * self.ts)
        keep = slice(res.t.size - self.samples, None)
        return SimulationResult(
            res.t[keep] - res.t[keep][0],
            res.sp[:, keep],
            res.op[:, keep],
            res.mv[:, keep],
            res.pv[:, keep],
            res.names,
        )


def _noise(std: float, seed: int) -> Disturbance:
    return Disturbance("noise", std, at="measurement", seed=seed)


def synthetic_library(samples: int = 4000) -> tuple[SyntheticCase, ...]:
    """The labelled library: stiction cases and the confounders.

    Stiction: each process with He and Kano valves of S in {2, 4, 8} % and
    J = S/2 (and J = S/4 for the He valve at S = 8), at two sampling
    intervals and two noise levels.  No stiction: the same processes with a
    healthy valve and an external sinusoidal disturbance at three periods,
    with aggressive tuning (a lightly damped linear loop driven by noise), or
    with noise only.  Every case has ``samples`` samples after warm-up;
    noise seeds are fixed so the library is reproducible.
    """
    cases: list[SyntheticCase] = []
    seed = 100
    for pname, proc in PROCESSES.items():
        sound = PIDController.ideal(proc.Kc, proc.Ti)
        for ts in proc.sampling:
            valves: list[tuple[str, ValveModel, float, float]] = []
            for S in (2.0, 4.0, 8.0):
                J = S / 2.0
                valves.append((f"he-S{S:g}-J{J:g}", HeValve((S + J) / 2, (S - J) / 2), S, J))
                valves.append((f"kano-S{S:g}-J{J:g}", KanoValve(S, J), S, J))
            valves.append(("he-S8-J2", HeValve(5.0, 3.0), 8.0, 2.0))
            for vname, valve, S, J in valves:
                seed += 1
                noise_std = proc.noise_levels[seed % 2]
                cases.append(
                    SyntheticCase(
                        f"{pname}-{vname}-ts{ts:g}", "stiction", "stiction", proc.kind, ts,
                        S, J, valve, proc.model, sound, (_noise(noise_std, seed),), samples,
                    )
                )
            for k, period in enumerate(proc.disturbance_periods):
                seed += 1
                sine = Disturbance("sine", 2.0, at="output", period=period, phase=0.3 * k)
                cases.append(
                    SyntheticCase(
                        f"{pname}-sine{period:g}s-ts{ts:g}", "no_stiction", "external_disturbance",
                        proc.kind, ts, None, None, IdealValve(), proc.model, sound,
                        (sine, _noise(0.1, seed)), samples,
                    )
                )
            seed += 1
            aggressive = PIDController.ideal(proc.aggressive_Kc, proc.aggressive_Ti)
            cases.append(
                SyntheticCase(
                    f"{pname}-aggressive-ts{ts:g}", "no_stiction", "aggressive_tuning", proc.kind,
                    ts, None, None, IdealValve(), proc.model, aggressive,
                    (_noise(0.2, seed), Disturbance("noise", 0.5, at="input", seed=seed + 1)),
                    samples,
                )
            )
            seed += 2
            cases.append(
                SyntheticCase(
                    f"{pname}-noise-ts{ts:g}", "no_stiction", "noise", proc.kind, ts, None, None,
                    IdealValve(), proc.model, sound,
                    (_noise(0.2, seed), Disturbance("noise", 0.5, at="input", seed=seed + 1)),
                    samples,
                )
            )
    names = [c.name for c in cases]
    assert len(set(names)) == len(names), "case names must be unique"
    return tuple(cases)

