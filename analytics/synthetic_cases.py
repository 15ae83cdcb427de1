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

:func:`synthetic_library` is the limit-cycle library: every sticky valve
there makes the loop oscillate.  :func:`transient_library` holds what real
plant data mostly shows instead: stiction without a regular cycle -- the
valve holds while slow integral action ramps OP through the stick band,
PV stays flat but for noise, then the valve slips and PV jumps, a few such
episodes per window started by set-point and load changes -- and healthy
loops that look alike (set-point and load steps, slow disturbances, large
noise, historian compression, coarse quantisation, saturation, P-only
control), which a detector must leave alone.

Examples
--------
>>> cases = synthetic_library()
>>> sorted({c.label for c in cases})
['no_stiction', 'stiction']
>>> case = next(c for c in cases if c.name == "flow-he-S4-J2-ts0.5")
>>> case.S, case.J, case.process_type
(4.0, 2.0, 'self-regulating')
>>> transient = transient_library()
>>> sorted({c.cause for c in transient if c.label == "stiction"})
['stick_jump']
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, TypedDict

import numpy as np

from analytics.lti import TransferFunction
from analytics.simulation import Disturbance, Loop, PIDController, SimulationResult, simulate
from analytics.types import FloatArray, ProcessType
from analytics.valves import HeValve, IdealValve, KanoValve, ValveModel

__all__ = [
    "PROCESSES",
    "SWEEP_SCENARIOS",
    "TRANSIENT_PROCESSES",
    "SyntheticCase",
    "synthetic_library",
    "transient_library",
    "transient_sweep",
    "window_start",
]

Label = Literal["stiction", "no_stiction"]

WARM_UP = 0.2
"""Default fraction of each simulation dropped as start-up transient."""


@dataclass(frozen=True)
class _Process:
    """A process with a PI tuning that is well damped with a healthy valve."""

    model: TransferFunction
    kind: ProcessType
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
        :func:`synthetic_library`: ``"stiction"``, ``"external_disturbance"``,
        ``"aggressive_tuning"`` or ``"noise"`` (no oscillation).
        :func:`transient_library`: ``"stick_jump"`` (stiction) or one of
        ``"setpoint_steps"``, ``"load_steps"``, ``"slow_disturbance"``,
        ``"noisy_flow"``, ``"compression"``, ``"quantisation"``,
        ``"saturation"``, ``"p_only"``.
    process_type : {"self-regulating", "integrating"}
    ts : float
        Sampling interval in seconds.
    S, J : float or None
        True stick band and slip jump in % of OP span (None without
        stiction).
    valve : ValveModel
    process : TransferFunction
    controller : PIDController
    disturbances : tuple of Disturbance
        Loads and sensor noise; times in simulation time (warm-up included).
    samples : int
        Samples of the window that :meth:`simulate` returns (after warm-up).
    setpoint : tuple of (time, value) or None
        Set-point schedule of steps in simulation time (warm-up included, see
        :func:`window_start`); None for the single step to 51 % at ``5 ts``
        of :func:`synthetic_library`; empty for a constant 50 %.
    pv_quantum : float or None
        Recorded PV rounded to multiples of this (% of span): a coarse A/D
        converter or a historian storing few digits.  None: not rounded.
    pv_compression, op_compression : float or None
        Historian deadband compression (% of span) of the recorded PV / OP:
        the last recorded value is held until the signal moves more than this
        away from it.  Applied after ``pv_quantum``.  MV is never altered: it
        is the true valve position.  None: not compressed.
    manual : tuple of (start, end)
        Stretches in manual (:attr:`analytics.simulation.Loop.manual`), in s
        of the returned window (the warm-up is always automatic).
    """

    name: str
    label: Label
    cause: str
    process_type: ProcessType
    ts: float
    S: float | None
    J: float | None
    valve: ValveModel
    process: TransferFunction
    controller: PIDController
    disturbances: tuple[Disturbance, ...]
    samples: int
    setpoint: tuple[tuple[float, float], ...] | None = None
    pv_quantum: float | None = None
    pv_compression: float | None = None
    op_compression: float | None = None
    manual: tuple[tuple[float, float], ...] = ()

    def simulate(self, warm_up: float = WARM_UP) -> SimulationResult:
        """Simulate the loop, drop the first ``warm_up`` fraction (start-up
        transient) and apply the recording effects (quantisation, compression)."""
        n_total = _total_samples(self.samples, warm_up)
        shift = (n_total + 1 - self.samples) * self.ts  # the window's first sample (kept below)
        loop = Loop(
            self.controller,
            self.valve,
            setpoint=[(5.0 * self.ts, 51.0)] if self.setpoint is None else self.setpoint,
            pv_bias=50.0,
            disturbances=self.disturbances,
            name=self.name,
            manual=tuple((start + shift, end + shift) for start, end in self.manual),
        )
        res = simulate(self.process, loop, dt=self.ts, duration=n_total * self.ts)
        keep = slice(res.t.size - self.samples, None)
        op, pv = res.op[:, keep], res.pv[:, keep]
        if self.pv_quantum is not None:
            pv = np.round(pv / self.pv_quantum) * self.pv_quantum
        if self.pv_compression is not None:
            pv = _deadband_compress(pv, self.pv_compression)
        if self.op_compression is not None:
            op = _deadband_compress(op, self.op_compression)
        return SimulationResult(
            res.t[keep] - res.t[keep][0],
            res.sp[:, keep],
            op,
            res.mv[:, keep],
            pv,
            res.names,
        )


def _total_samples(samples: int, warm_up: float) -> int:
    """Samples simulated so that ``samples`` remain after the warm-up fraction."""
    return round(samples / (1.0 - warm_up))


def window_start(samples: int, ts: float, warm_up: float = WARM_UP) -> float:
    """Simulation time (s) of the first sample that :meth:`SyntheticCase.simulate` keeps."""
    return (_total_samples(samples, warm_up) - samples) * ts


def _deadband_compress(x: FloatArray, deadband: float) -> FloatArray:
    """Deadband compression along the last axis: a historian that records a
    new value only when the signal has moved more than ``deadband`` from the
    last recorded one, and replays the recorded value in between."""
    out = np.array(x, dtype=np.float64, copy=True)
    for row in out.reshape(-1, out.shape[-1]):
        held = row[0]
        for k in range(1, row.size):
            if abs(row[k] - held) > deadband:
                held = row[k]
            else:
                row[k] = held
    return out


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


@dataclass(frozen=True)
class _TransientProcess:
    """A loop of :func:`transient_library` with a loose, slow tuning.

    ``Kc``/``Ti`` is a PI tuning with integral action so slow that a sticky
    valve is ramped through its band over minutes (flow) or tens of minutes
    (level) instead of cycling; ``p_only_Kc`` the gain of its P-only variant.
    ``sp_step`` and ``load_step`` size the set-point and load changes (% of
    span); ``noise_levels`` are the PV sensor noise stds cycled over its cases.
    """

    model: TransferFunction
    kind: ProcessType
    Kc: float
    Ti: float
    p_only_Kc: float
    sp_step: float
    load_step: float
    noise_levels: tuple[float, ...]


TRANSIENT_PROCESSES: dict[str, _TransientProcess] = {
    # the flow process of PROCESSES with a sluggish PI (Ti = 19 x the time constant)
    "flow": _TransientProcess(
        PROCESSES["flow"].model, "self-regulating", 0.3, 150.0, 1.0, 1.5, 1.5,
        (0.05, 0.1, 0.2, 0.3),
    ),
    # the level process of PROCESSES with a gentle, almost proportional PI
    "level": _TransientProcess(
        PROCESSES["level"].model, "integrating", 0.3, 5000.0, 0.5, 3.0, 1.5,
        (0.05, 0.1, 0.2),
    ),
}
"""Processes of :func:`transient_library`: the flow and level processes of
:data:`PROCESSES` with the loose tunings common on real plants."""


Events = tuple[tuple[tuple[float, float], ...], tuple[Disturbance, ...]]


def _events(
    scenario: str, proc: _TransientProcess, samples: int, ts: float, seed: int
) -> Events:
    """Set-point schedule and load disturbances of a scenario in the window.

    ``"sp-steps"``: three set-point steps; ``"sp-ramp"``: a set-point ramp up
    and one down, each a staircase of one step per 10 samples (a DCS ramps
    its set point in small increments); ``"load-steps"``: two steps of load
    on the process input (a supply-pressure or inflow change) and one on the
    output; ``"slow-sine"``: a load on the input with a period of 40 % of the
    window; ``"random-walk"``: an input load wandering as a random walk
    (seeded steps every 20 samples, about 3 % over the window);
    ``"saturation"``: a large input load for 30 % of the window that the
    valve, running at 85 % open, cannot compensate.  Times are fractions of
    the window, so every event falls inside it whatever ``samples``.
    """
    t0, span = window_start(samples, ts), samples * ts
    a, b = proc.sp_step, proc.load_step

    def at(fraction: float) -> float:
        return t0 + fraction * span

    def ramp(start: float, stop: float, v0: float, v1: float) -> list[tuple[float, float]]:
        n = max(1, round((stop - start) * samples / 10))
        return [
            (at(start + (stop - start) * i / n), v0 + (v1 - v0) * i / n) for i in range(1, n + 1)
        ]

    if scenario == "sp-steps":
        return ((at(0.1), 50.0 + a), (at(0.4), 50.0 - 0.5 * a), (at(0.7), 50.0 + 0.5 * a)), ()
    if scenario == "sp-ramp":
        return tuple(ramp(0.1, 0.35, 50.0, 50.0 + a) + ramp(0.6, 0.8, 50.0 + a, 50.0 - 0.5 * a)), ()
    if scenario == "load-steps":
        loads = (
            Disturbance("step", b, at="input", time=at(0.15)),
            Disturbance("step", -1.6 * b, at="input", time=at(0.45)),
            Disturbance("step", 0.8 * b, at="output", time=at(0.75)),
        )
        return (), loads
    if scenario == "slow-sine":
        return (), (Disturbance("sine", 2.0, at="input", period=0.4 * span),)
    if scenario == "random-walk":
        n_total = _total_samples(samples, WARM_UP)
        steps = np.random.default_rng((seed, 1)).normal(0.0, 0.25, size=n_total // 20)
        walk = tuple(
            Disturbance("step", float(step), at="input", time=20 * k * ts)
            for k, step in enumerate(steps)
        )
        return (), walk
    if scenario == "saturation":
        return (), (
            Disturbance("step", -25.0, at="input", time=at(0.3)),
            Disturbance("step", 25.0, at="input", time=at(0.6)),
        )
    raise ValueError(f"unknown scenario {scenario!r}")


# Sticky transient cases: (process, valve model, S, J, scenario, ts, control)
_STICKY: tuple[tuple[str, str, float, float, str, float, str], ...] = (
    ("flow", "he", 0.5, 0.25, "sp-steps", 1.0, "pi"),
    ("flow", "kano", 1.0, 0.5, "sp-steps", 2.0, "pi"),
    ("flow", "he", 2.0, 0.5, "sp-steps", 1.0, "pi"),
    ("flow", "kano", 3.0, 1.5, "sp-steps", 1.0, "pi"),
    ("flow", "he", 2.0, 0.0, "sp-steps", 2.0, "pi"),
    ("flow", "he", 1.5, 0.5, "sp-ramp", 1.0, "pi"),
    ("flow", "kano", 2.0, 1.0, "sp-ramp", 2.0, "pi"),
    ("flow", "he", 1.0, 0.25, "load-steps", 2.0, "pi"),
    ("flow", "kano", 2.0, 0.5, "load-steps", 1.0, "pi"),
    ("flow", "he", 3.0, 1.0, "load-steps", 1.0, "pi"),
    ("flow", "kano", 1.0, 0.0, "load-steps", 2.0, "pi"),
    ("flow", "he", 2.0, 1.0, "sp-ramp", 1.0, "p"),
    ("flow", "kano", 1.0, 0.5, "sp-steps", 2.0, "p"),
    ("level", "he", 1.0, 0.25, "sp-steps", 2.0, "pi"),
    ("level", "kano", 2.0, 0.25, "sp-steps", 5.0, "pi"),
    ("level", "he", 3.0, 1.0, "load-steps", 2.0, "pi"),
    ("level", "kano", 0.5, 0.25, "load-steps", 5.0, "pi"),
    ("level", "he", 2.0, 0.5, "sp-ramp", 5.0, "pi"),
    ("level", "he", 1.0, 0.5, "sp-steps", 2.0, "p"),
    ("level", "kano", 2.0, 0.5, "load-steps", 5.0, "p"),
)

# Healthy look-alikes: (process, cause, scenario, ts, control, noise std or None, recording)
class _Recording(TypedDict, total=False):
    """The recording effects of a case (:class:`SyntheticCase`)."""

    pv_quantum: float
    pv_compression: float
    op_compression: float


_HEALTHY: tuple[tuple[str, str, str, float, str, float | None, _Recording], ...] = (
    ("flow", "setpoint_steps", "sp-steps", 1.0, "pi", None, {}),
    ("flow", "setpoint_steps", "sp-ramp", 2.0, "pi", None, {}),
    ("flow", "load_steps", "load-steps", 1.0, "pi", None, {}),
    ("flow", "load_steps", "load-steps", 2.0, "pi", None, {}),
    ("flow", "noisy_flow", "sp-steps", 1.0, "pi", 0.8, {}),
    ("flow", "noisy_flow", "load-steps", 2.0, "pi", 1.5, {}),
    ("flow", "compression", "sp-steps", 1.0, "pi", 0.1, {"pv_compression": 0.3}),
    ("flow", "compression", "load-steps", 2.0, "pi", None,
     {"pv_compression": 0.5, "op_compression": 0.2}),
    ("flow", "quantisation", "sp-steps", 1.0, "pi", None, {"pv_quantum": 0.1}),
    ("flow", "quantisation", "load-steps", 2.0, "pi", None, {"pv_quantum": 0.25}),
    ("flow", "slow_disturbance", "slow-sine", 1.0, "pi", None, {}),
    ("flow", "slow_disturbance", "random-walk", 2.0, "pi", None, {}),
    ("flow", "saturation", "saturation", 1.0, "pi", None, {}),
    ("flow", "p_only", "sp-steps", 1.0, "p", None, {}),
    ("level", "setpoint_steps", "sp-steps", 5.0, "pi", None, {}),
    ("level", "load_steps", "load-steps", 2.0, "pi", None, {}),
    ("level", "slow_disturbance", "slow-sine", 5.0, "pi", None, {}),
    ("level", "saturation", "saturation", 2.0, "pi", None, {}),
    ("level", "compression", "load-steps", 5.0, "pi", None, {"pv_compression": 0.25}),
    ("level", "quantisation", "sp-steps", 2.0, "pi", None, {"pv_quantum": 0.2}),
    ("level", "p_only", "load-steps", 5.0, "p", None, {}),
)

_HEALTHY_TAGS = {
    "noisy_flow": "-noisy",
    "compression": "-compressed",
    "quantisation": "-quantised",
    "p_only": "-p-only",
}
"""Name suffixes of the healthy causes that the scenario name does not tell."""


def transient_library(samples: int = 2000) -> tuple[SyntheticCase, ...]:
    """Stick-jump stiction without a regular limit cycle, and healthy look-alikes.

    Real plant data mostly shows stiction as isolated episodes: the valve
    holds while slow integral action ramps OP through the stick band, PV
    stays flat but for noise, then the valve slips and PV jumps; set-point
    and load changes start the episodes.  These cases are built that way.

    Stiction (cause ``"stick_jump"``): He and Kano valves with S of 0.5-3 %
    and mostly 0 < J <= S/2 (two pure deadbands, J = 0), on the flow and the
    level process of :data:`TRANSIENT_PROCESSES` with sluggish PI or P-only
    control, driven by set-point steps, set-point ramps or load steps, with
    sensor noise of 0.05-0.3 % of span.  The flow loop (self-regulating)
    settles between events in a few stick-jump steps; the level loop
    (integrating) cannot settle with a sticky valve and hunts, but with its
    gentle gain in slow, irregular stick-jump episodes, not a regular cycle.

    No stiction, all with a healthy valve and the same loops, events and
    tunings, so only the valve differs: ``"setpoint_steps"`` (steps and
    ramps), ``"load_steps"``, ``"slow_disturbance"`` (a slow sine and a
    random-walk load, much slower than the loop), ``"noisy_flow"`` (0.8-1.5 %
    sensor noise), ``"compression"`` (historian deadband compression of PV,
    once of OP too: PV held flat while OP moves, then a jump -- the pattern
    of stiction), ``"quantisation"`` (PV on a 0.1-0.25 % lattice),
    ``"saturation"`` (a large load drives OP to its limit for a stretch) and
    ``"p_only"`` (P-only control with its offsets).

    Every case has ``samples`` samples after warm-up (the events are placed
    at fixed fractions of the window; the stick-jump behaviour is checked at
    the default length); noise seeds are fixed so the library is
    reproducible.
    """
    cases: list[SyntheticCase] = []
    seed = 1000

    def controller(proc: _TransientProcess, control: str, **options: float) -> PIDController:
        if control == "p":
            return PIDController.ideal(proc.p_only_Kc, **options)
        return PIDController.ideal(proc.Kc, proc.Ti, **options)

    for pname, vkind, S, J, scenario, ts, control in _STICKY:
        seed += 1
        proc = TRANSIENT_PROCESSES[pname]
        valve: ValveModel = HeValve((S + J) / 2, (S - J) / 2) if vkind == "he" else KanoValve(S, J)
        setpoint, loads = _events(scenario, proc, samples, ts, seed)
        noise = _noise(proc.noise_levels[seed % len(proc.noise_levels)], seed)
        tag = "-p-only" if control == "p" else ""
        cases.append(
            SyntheticCase(
                f"{pname}-{vkind}-S{S:g}-J{J:g}-{scenario}{tag}-ts{ts:g}", "stiction",
                "stick_jump", proc.kind, ts, S, J, valve, proc.model, controller(proc, control),
                (*loads, noise), samples, setpoint,
            )
        )
    for pname, cause, scenario, ts, control, noise_std, recording in _HEALTHY:
        seed += 1
        proc = TRANSIENT_PROCESSES[pname]
        setpoint, loads = _events(scenario, proc, samples, ts, seed)
        std = proc.noise_levels[seed % len(proc.noise_levels)] if noise_std is None else noise_std
        bias = {"op_bias": 85.0} if scenario == "saturation" else {}
        tag = _HEALTHY_TAGS.get(cause, "")
        cases.append(
            SyntheticCase(
                f"{pname}-ideal-{scenario}{tag}-ts{ts:g}", "no_stiction", cause,
                proc.kind, ts, None, None, IdealValve(), proc.model,
                controller(proc, control, **bias), (*loads, _noise(std, seed)), samples,
                setpoint, **recording,
            )
        )
    names = [c.name for c in cases]
    assert len(set(names)) == len(names), "case names must be unique"
    return tuple(cases)


SWEEP_SCENARIOS = ("sp-steps", "sp-ramp", "load-steps", "slow-sine", "random-walk", "saturation")
"""Scenarios of :func:`transient_sweep` (:func:`_events`)."""


def transient_sweep(seeds: range = range(3001, 3013), samples: int = 2000
                    ) -> tuple[SyntheticCase, ...]:
    """The flow and level loops of :func:`transient_library` in every scenario of
    :data:`SWEEP_SCENARIOS`, on other seeds, each with a He valve (S 2, J 0.5), a
    Kano valve (S 2, J 0.5) and a healthy valve.

    A check of how the transient detectors generalise beyond the library they
    were tuned on: the same loops and events, new noise and random walks, and
    every scenario with every valve (the library pairs each scenario with some
    valves only).  Named ``{process}-{valve}-{scenario}-seed{seed}``; PI control
    at ts 1 s (flow) and 5 s (level), the library's sensor noise levels cycled
    by seed.
    """
    valves: dict[str, tuple[ValveModel, Label]] = {
        "he": (HeValve(1.25, 0.75), "stiction"),
        "kano": (KanoValve(2.0, 0.5), "stiction"),
        "ideal": (IdealValve(), "no_stiction"),
    }
    cases: list[SyntheticCase] = []
    for pname, ts in (("flow", 1.0), ("level", 5.0)):
        proc = TRANSIENT_PROCESSES[pname]
        for scenario in SWEEP_SCENARIOS:
            for seed in seeds:
                setpoint, loads = _events(scenario, proc, samples, ts, seed)
                noise = _noise(proc.noise_levels[seed % len(proc.noise_levels)], seed)
                for vname, (valve, label) in valves.items():
                    S, J = (None, None) if label == "no_stiction" else (2.0, 0.5)
                    cases.append(SyntheticCase(
                        f"{pname}-{vname}-{scenario}-seed{seed}", label,
                        "stick_jump" if S else scenario, proc.kind, ts, S, J, valve,
                        proc.model, PIDController.ideal(proc.Kc, proc.Ti), (*loads, noise),
                        samples, setpoint,
                    ))
    return tuple(cases)
