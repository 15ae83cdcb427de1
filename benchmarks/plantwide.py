"""Multi-loop stiction detection (thesis chapter 2): accuracy and speed.

Prints, in one run:

1. the simulated 3x3 column (thesis section 2.4) with every combination of
   sticky valves and with an external sinusoid instead: the valves named,
   and for the thesis scenarios with one, two and three sticky valves the
   counterparts of thesis Tables 2.4-2.8 beside the published values (the
   held-out error of the shape decomposition for k = 1..3, the structures,
   the surrogate nonlinearity index of every OP and PV);
2. the Tennessee Eastman runs (../shared/data/tep): the valves named in
   normal operation and with the reactor (IDV 14) or condenser (IDV 15)
   cooling-water valve sticking;
3. the unit's own model (issue 22, :mod:`analytics.plantwide.fingerprint`):
   every non-empty sticky set of the column with S and J drawn within 30 % of
   Table 2.3, on seeds 200-203 (the penalty and the distortion floor were
   chosen on 100-103, the tests use 7), with the exact matrix and with every
   gain 20 % off: the right set named by the fingerprint alone and by the
   whole unit diagnosis with and without the model, the named valves' S, the
   external sines, and the time of one localisation;
4. medians of repeated runs: the surrogate index of 8 signals of 2,000
   samples with M = 50 (one core), the grouping of the 52 TEP signals and
   the whole unit diagnosis of the column.

Run with ``make bench`` or ``.venv/bin/python benchmarks/plantwide.py``
(``... plantwide.py model`` for part 3 alone, ``... plantwide.py oracle`` for
whether a replay of the sticky valves with their true S, J and a fitted stick state
would see valve 3 beside another, ``... plantwide.py why`` for the
study of why the fingerprint confuses sets, on the calibration seeds,
``... plantwide.py score`` for the fingerprint's confusion per sticky set on the
calibration seeds and ``... plantwide.py score held-out`` on the scored ones,
``... plantwide.py sync`` for whether a sticky valve replayed from its OP meets the
simulated MV, ``... plantwide.py replay`` for the time-domain replay of every sticky set
(:mod:`analytics.plantwide.replay`) with every penalty tried on the calibration seeds,
and ``... plantwide.py replay held-out`` with the chosen one on the scored seeds).
"""

from __future__ import annotations

import dataclasses
import os

# One core for the speed figures (set before numpy and numba load their pools).
for variable in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                 "MKL_NUM_THREADS"):
    os.environ.setdefault(variable, "1")

import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Iterator  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.signal import fftconvolve, lfilter  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from analytics.limit_cycle import ProcessMatrix  # noqa: E402
from analytics.lti import DiscreteEntry, TransferFunction, discretise  # noqa: E402
from analytics.plantwide import (  # noqa: E402
    GroupDiagnosis,
    UnitDiagnosis,
    UnitModel,
    diagnose_unit,
    find_oscillation_groups,
    linear_check,
    locate_sticky_valves,
    measure_fingerprint,
)
from analytics.plantwide.fingerprint import _frequency_response  # noqa: E402
from analytics.plantwide.replay import (  # noqa: E402
    VALVE_PENALTY as REPLAY_PENALTY,
)
from analytics.plantwide.replay import (  # noqa: E402
    ReplayLocalisation,
    replay_sticky_sets,
)
from analytics.scenarios import COLUMN_VALVES, column3x3  # noqa: E402
from analytics.simulation import ClosedLoopModel, Disturbance  # noqa: E402
from analytics.stiction.surrogate import surrogate_nonlinearity_index  # noqa: E402
from analytics.valves import HeValve  # noqa: E402

TEP = ROOT.parent / "shared" / "data" / "tep"
TEP_PV_OF = {1: 26, 2: 27, 3: 1, 4: 4, 5: 13, 6: 10, 7: 12, 8: 15, 9: 19, 10: 9, 11: 17}
"""XMV(j) -> the XMEAS it controls (from d00 normal operation; see the tests)."""

THESIS_TABLE_2_8 = {  # surrogate index, OP1-3 then PV1-3
    (1,): (1.4478, 0.1150, 1.4499, 11.0361, 7.2391, 8.2083),
    (1, 2): (1.013, -0.8190, -0.2103, 12.3109, 9.4891, 7.4260),
    (1, 2, 3): (-0.2138, 0.2513, 0.9936, 9.3172, 6.3321, 9.0021),
}
THESIS_TABLE_2_7 = {
    (1,): ("tri+sin+sin", "tri+sin+sin", "tri+sin+sin"),
    (1, 2): ("tri+tri+sin", "tri+squ+sin", "tri+tri+sin"),
    (1, 2, 3): ("tri+tri+squ", "tri+tri+squ", "tri+tri+squ"),
}
THESIS_MSE = {  # Tables 2.4-2.6: MSE of PV1-3 with k = 1, 2, 3 shapes (scenarios A, B, C)
    (1,): ((0.0002, 0.0011, 0.0014), (0.0051, 0.0037, 0.0065), (1.2981, 1.1350, 1.4887)),
    (1, 2): ((0.0001, 0.0001, 0.0006), (0.0006, 0.0002, 0.0003), (1.4960, 0.2450, 0.8707)),
    (1, 2, 3): ((0.0001, 0.0005, 0.0002), (0.0007, 0.0047, 0.0006), (1.9160, 0.5854, 0.5007)),
}
SHORT = {"square": "squ", "triangular": "tri", "sinusoidal": "sin"}


def median_time(run: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def column_unit(model: ClosedLoopModel) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    run = model.run()
    late = run.t >= 2000.0  # after the start-up transient
    return {name: (run.op[i][late], run.pv[i][late]) for i, name in enumerate(run.names)}


def with_sine(loop: int, at: str, period: float) -> ClosedLoopModel:
    model = column3x3(sticky=())
    loops = list(model.loops)
    loops[loop] = dataclasses.replace(
        loops[loop], disturbances=(*loops[loop].disturbances, Disturbance("sine", 1.0, at=at,
                                                                          period=period)))
    return dataclasses.replace(model, loops=tuple(loops))


def healthy_columns() -> Iterator[tuple[str, dict[str, tuple[np.ndarray, np.ndarray]],
                                          UnitModel]]:
    """The healthy column with an external sine (at input 1, at output 2) and with noise
    only, each with the unit's model exact and with its gains 20 % off: ``(label, the
    unit's OP and PV per loop, the model)``."""
    for label, model in (("healthy, sine at input 1", with_sine(0, "input", 200.0)),
                         ("healthy, sine at output 2", with_sine(1, "output", 150.0)),
                         ("healthy, noise only", column3x3(sticky=()))):
        unit = column_unit(model)
        for error in (0.0, 0.2):
            yield f"{label}, gains {error:.0%} off", unit, unit_model(model, gain_error=error)


def thesis_tables(sticky: tuple[int, ...], result: UnitDiagnosis) -> None:
    print(f"  thesis Tables 2.4-2.8 for {len(sticky)} sticky valve(s):")
    indices: dict[str, float] = {}
    for group in result.groups:
        for signal, value in group.ranking:
            indices.setdefault(signal, value)
    ours = [indices.get(f"{r}_loop{i}") for r in ("op", "pv") for i in (1, 2, 3)]
    print("    Table 2.8 N      " + " ".join(f"{s:>7s}" for s in
                                            ("OP1", "OP2", "OP3", "PV1", "PV2", "PV3")))
    print("      thesis         " + " ".join(f"{v:7.2f}" for v in THESIS_TABLE_2_8[sticky]))
    print("      ours           " + " ".join("      -" if v is None else f"{v:7.2f}"
                                             for v in ours))
    for i, mse in enumerate(THESIS_MSE[sticky], start=1):
        print(f"    Tables 2.4-2.6 PV{i}: thesis MSE k=1..3 {mse} -> best k = "
              f"{int(np.argmin(mse)) + 1}; structure {THESIS_TABLE_2_7[sticky][i - 1]}")
    for group in result.groups:
        d = group.decomposition
        if d is None:
            continue
        print(f"    ours, cycle {group.period_s:.0f} s: shapes k = {d.k} of {d.n}")
        for name, errors in d.per_signal_error.items():
            structure = "+".join(SHORT[s] for s in d.structures[name])
            print(f"      {name}: held-out error k=0..{len(errors) - 1} "
                  f"{tuple(round(e, 3) for e in errors)}; structure {structure}")


def group_line(group: GroupDiagnosis) -> str:
    shapes = "-" if group.decomposition is None else str(group.decomposition.k)
    return (f"{group.period_s:7.1f} s  loops {','.join(group.loops) or '-':22s} shapes k={shapes}"
            f"  named {','.join(group.sticky_valves) or '-'}")


def column() -> None:
    print("== simulated 3x3 column (thesis Eq. 2.10, Table 2.3 He valves, noise var 0.01) ==")
    cases: list[tuple[str, tuple[int, ...], ClosedLoopModel]] = [
        (f"sticky {','.join(map(str, s))}", s, column3x3(sticky=s))
        for s in ((1,), (1, 2), (1, 2, 3), (2,), (3,), (1, 3), (2, 3))
    ]
    cases += [
        ("healthy, sine at input 1", (), with_sine(0, "input", 200.0)),
        ("healthy, sine at output 2", (), with_sine(1, "output", 150.0)),
    ]
    right = 0
    for label, sticky, model in cases:
        result = diagnose_unit(column_unit(model), 0.5)
        truth = {f"loop{i}" for i in sticky}
        named = {f.loop for f in result.sticky_valves}
        right += named == truth
        mark = "ok" if named == truth else "XX"
        print(f"{mark} {label:27s} true k={len(truth)}  named k={result.k}: "
              + ", ".join(f"{f.loop} ({f.confidence:.2f}, S={f.S:.2f})"
                          if f.S is not None else f.loop for f in result.sticky_valves))
        for group in result.groups:
            print("     " + group_line(group))
        if sticky in THESIS_TABLE_2_8:
            thesis_tables(sticky, result)
    print(f"right valves in {right} of {len(cases)} cases\n")


SCORED_SEEDS = (200, 201, 202, 203)
"""Seeds of the model benchmark: not those the fingerprint's constants were chosen on
(100-103) nor the tests' (7)."""
STICKY_SETS = ((1,), (2,), (3,), (1, 2), (1, 3), (2, 3), (1, 2, 3))


def randomised_column(sticky: tuple[int, ...], seed: int
                      ) -> tuple[ClosedLoopModel, dict[str, float]]:
    """The column with the valves of ``sticky`` given fs and fd within 30 % of Table 2.3;
    the true S = fs + fd of each."""
    rng = np.random.default_rng(seed)
    model = column3x3(sticky=sticky, seed=seed)
    loops = list(model.loops)
    true_s = {}
    for i in sticky:
        nominal = COLUMN_VALVES[i - 1]
        fs = nominal.fs * rng.uniform(0.7, 1.3)
        fd = min(nominal.fd * rng.uniform(0.7, 1.3), 0.9 * fs)
        loops[i - 1] = dataclasses.replace(loops[i - 1], valve=HeValve(fs, fd))
        true_s[f"loop{i}"] = fs + fd
    return dataclasses.replace(model, loops=tuple(loops)), true_s


def unit_model(model: ClosedLoopModel, *, gain_error: float = 0.0, seed: int = 0) -> UnitModel:
    """The unit model of ``model``; with ``gain_error`` each process gain is off by that
    share, up or down at random."""
    rng = np.random.default_rng(seed + 999)
    assert isinstance(model.process, tuple)

    def off(g: TransferFunction | None) -> TransferFunction | None:
        if g is None:
            return None
        factor = 1.0 + gain_error * rng.choice([-1.0, 1.0])
        return dataclasses.replace(g, num=tuple(c * factor for c in g.num))

    process = tuple(tuple(off(g) for g in row) for row in model.process)
    return UnitModel(tuple(loop.name for loop in model.loops), process,
                     tuple(loop.controller for loop in model.loops))


CALIBRATION_SEEDS = (100, 101, 102, 103)
"""Seeds the fingerprint's constants were chosen on; the confusion study reads them, so
that the held-out figures of :func:`model_localisation` stay untouched."""

NEARLY_HEALTHY = 0.05
"""A sticky valve whose describing function lies within this distance of 1 at its
measured OP amplitude is close to invisible at the fundamental."""


def valve_gains(process: ProcessMatrix, unit_op: list[np.ndarray], unit_pv: list[np.ndarray],
                period_s: float) -> np.ndarray:
    """Each valve's gain ``u_k / x_k`` at the fundamental read through the model,
    ``u = G(jw)^-1 y`` (thesis Eq. 3.11 solved for the valve outputs), with the
    zero-order hold's half sample of dead time."""
    fp = measure_fingerprint(unit_op, unit_pv, 0.5, period_s)
    g = _frequency_response(process, fp.omega) * np.exp(-0.25j * fp.omega)
    return np.linalg.solve(g, np.array(fp.pv)) / np.array(fp.op)


def confusion() -> None:
    """Why sets are confused: on the calibration seeds, each valve's gain at the
    fundamental as simulated (MV over OP), as read through the exact model and through
    the model with every gain 20 % off, the condition number of G(jw), and the OP
    amplitude against the valve's S."""
    print("== why sets are confused: valve gains at the fundamental (calibration seeds) ==")
    invisible, total, errors_exact, errors_off, conditions = 0, 0, [], [], []
    for seed in CALIBRATION_SEEDS:
        for sticky in STICKY_SETS:
            model, true_s = randomised_column(sticky, seed)
            run = model.run()
            late = run.t >= 2000.0
            op, pv, mv = list(run.op[:, late]), list(run.pv[:, late]), list(run.mv[:, late])
            fp = measure_fingerprint(op, pv, 0.5)
            moved = measure_fingerprint(op, mv, 0.5, fp.period_s)
            truth = np.array(moved.pv) / np.array(moved.op)
            exact_model = unit_model(model).process
            exact = valve_gains(exact_model, op, pv, fp.period_s)
            off = valve_gains(unit_model(model, gain_error=0.2, seed=seed).process, op, pv,
                              fp.period_s)
            conditions.append(np.linalg.cond(_frequency_response(exact_model, fp.omega)))
            moving = np.abs(fp.op) >= 0.01 * np.abs(fp.op).max()
            errors_exact += list(np.abs(exact - truth)[moving])
            errors_off += list(np.abs(off - truth)[moving])
            for i in sticky:
                total += 1
                invisible += abs(truth[i - 1] - 1) < NEARLY_HEALTHY
            cell = lambda v: f"{abs(v):4.2f}<{np.degrees(np.angle(v)):4.0f}"  # noqa: E731
            bands = " ".join(f"{true_s.get(name, 0.0):4.1f}" for name in run.names)
            print(f"  seed {seed} sticky {','.join(map(str, sticky)):6s} P {fp.period_s:5.0f} s "
                  f"|OP| {' '.join(f'{abs(v):5.1f}' for v in fp.op)}  S {bands}")
            print(f"      N simulated {' '.join(map(cell, truth))}; through the model "
                  f"{' '.join(map(cell, exact))}; gains 20 % off {' '.join(map(cell, off))}")
    print(f"sticky valves nearly healthy at the fundamental (|N - 1| < {NEARLY_HEALTHY}): "
          f"{invisible} of {total}")
    print(f"valve gain read through the model, median error: exact {np.median(errors_exact):.3f},"
          f" gains 20 % off {np.median(errors_off):.2f}; condition number of G(jw) "
          f"{min(conditions):.0f}-{max(conditions):.0f}\n")


def model_localisation() -> None:
    print("== the unit's own model: harmonic-balance fingerprint (issue 22) ==")
    spec = unit_model(column3x3())
    check = linear_check(spec.process, spec.controllers, hold_delay=0.25)
    print(f"linear check, tunings 2.11-2.13: stable {check.stable}, margin {check.margin:.2f} "
          f"at {check.margin_omega:.3f} rad/s")
    tally: dict[str, list[bool]] = {}
    per_set: dict[tuple[str, tuple[int, ...]], list[bool]] = {}
    s_errors: dict[str, list[float]] = {"fingerprint": [], "unit diagnosis": []}
    for seed in SCORED_SEEDS:
        for sticky in STICKY_SETS:
            model, true_s = randomised_column(sticky, seed)
            unit = column_unit(model)
            truth = tuple(f"loop{i}" for i in sticky)
            line = []
            for label, error in (("exact", 0.0), ("gains 20 % off", 0.2)):
                um = unit_model(model, gain_error=error, seed=seed)
                found = locate_sticky_valves(unit, 0.5, um.process, um.controllers)
                ok = found.sticky_valves == truth
                tally.setdefault(f"fingerprint, {label}", []).append(ok)
                per_set.setdefault((label, sticky), []).append(ok)
                fit = found.fit_of(found.sticky_valves)
                if error == 0.0 and fit is not None:
                    s_errors["fingerprint"] += [s / true_s[v] - 1 for v, s in
                                                zip(fit.loops, fit.S, strict=True) if v in true_s]
                line.append(f"{label}: {','.join(found.sticky_valves) or '-'}")
            for label, with_model in (("unit diagnosis, data only", None),
                                      ("unit diagnosis with the model", unit_model(model))):
                result = diagnose_unit(unit, 0.5, model=with_model)
                named = tuple(sorted(f.loop for f in result.sticky_valves))
                tally.setdefault(label, []).append(named == truth)
                if with_model is not None:
                    s_errors["unit diagnosis"] += [f.S / true_s[f.loop] - 1 for f in
                                                   result.sticky_valves
                                                   if f.loop in true_s and f.S is not None]
                short = "unit, data only" if with_model is None else "unit with model"
                line.append(f"{short}: {','.join(named) or '-'}")
            print(f"  seed {seed} sticky {','.join(map(str, sticky)):6s} " + "; ".join(line))
    for label, oks in tally.items():
        print(f"right set, {label}: {sum(oks)} of {len(oks)} ({sum(oks) / len(oks):.0%})")
    for label in ("exact", "gains 20 % off"):
        print(f"  fingerprint per set ({label}): " + ", ".join(
            f"{{{','.join(map(str, s))}}} {sum(per_set[(label, s)])}/{len(per_set[(label, s)])}"
            for s in STICKY_SETS))
    for label, errors in s_errors.items():
        if errors:
            e = np.abs(errors)
            print(f"S of the truly sticky named valves ({label}): median error {np.median(e):.0%}, "
                  f"{np.mean(e <= 0.25):.0%} within 25 % ({len(e)} valves)")
    for label, unit, um in healthy_columns():
        found = locate_sticky_valves(unit, 0.5, um.process, um.controllers)
        print(f"  {label}: named {','.join(found.sticky_valves) or '-'} -- {found.note[:150]}")
    model = column3x3(sticky=(1, 2))
    unit, spec = column_unit(model), unit_model(model)
    locate = lambda: locate_sticky_valves(unit, 0.5, spec.process, spec.controllers)  # noqa: E731
    print(f"localisation of the 3x3 unit (linear check, 7 sets, forward check): "
          f"{median_time(locate, 5):.2f} s\n")


def score_sets(seeds: tuple[int, ...]) -> None:
    """The fingerprint's confusion per sticky set: every non-empty set of the column with S
    and J drawn within 30 % of Table 2.3 on ``seeds``, with the exact matrix and with every
    gain 20 % off (``plantwide.py score`` runs the calibration seeds 100-103, on which
    constants are chosen; ``plantwide.py score held-out`` the seeds 200-203, scored once)."""
    print(f"== fingerprint confusion per sticky set, seeds {seeds[0]}-{seeds[-1]} ==")
    times = []
    for label, error in (("exact gains", 0.0), ("gains 20 % off", 0.2)):
        right = 0
        for sticky in STICKY_SETS:
            named = []
            for seed in seeds:
                model, _ = randomised_column(sticky, seed)
                um = unit_model(model, gain_error=error, seed=seed)
                unit = column_unit(model)
                start = time.perf_counter()
                found = locate_sticky_valves(unit, 0.5, um.process, um.controllers)
                times.append(time.perf_counter() - start)
                named.append("".join(v.removeprefix("loop") for v in found.sticky_valves) or "-")
            ok = sum(n == "".join(map(str, sticky)) for n in named)
            right += ok
            counts = {n: named.count(n) for n in sorted(set(named))}
            print(f"  {label:14s} true {{{','.join(map(str, sticky))}}}: right {ok}/{len(named)};"
                  " named " + ", ".join(f"{{{','.join(n)}}} x{c}" if n != "-" else f"none x{c}"
                                        for n, c in counts.items()))
        print(f"  {label}: right set in {right} of {len(STICKY_SETS) * len(seeds)}")
    print(f"localisation time: median {statistics.median(times):.2f} s, max {max(times):.2f} s\n")


def he_replays(op: np.ndarray, fs: float, fd: float, starts: np.ndarray) -> np.ndarray:
    """He's valve (thesis Eq. 1.2) driven by a measured OP, one replay per starting
    position in ``starts`` (rows)."""
    y = np.array(starts, dtype=float)
    out = np.empty((y.size, op.size))
    for k, x in enumerate(op):
        y = np.where(x - y > fs, x - fd, np.where(y - x > fs, x + fd, y))
        out[:, k] = y
    return out


def replay_sync() -> None:
    """Whether a valve replayed from its measured OP reproduces the simulated MV.

    A replay of the sticky valves (the time-domain check of a candidate set, or a
    harmonic balance of the replayed MV's harmonics) needs the valve's MV.  With the
    true fs and fd, on the calibration seeds: the share of starting positions
    ``x0 + d`` (``d`` on a grid of 81 over ``[-fs, fs]``) from which the replay meets
    the simulated MV within the window, and the median sample where it does."""
    print("== replaying a sticky valve from its OP, true fs and fd (calibration seeds) ==")
    rows: dict[int, list[tuple[float, float, float]]] = {1: [], 2: [], 3: []}
    for seed in CALIBRATION_SEEDS:
        for sticky in STICKY_SETS:
            model, _ = randomised_column(sticky, seed)
            run = model.run()
            late = run.t >= 2000.0
            for i in sticky:
                valve = model.loops[i - 1].valve
                assert isinstance(valve, HeValve)
                op, mv = run.op[i - 1][late], run.mv[i - 1][late]
                half_range = (np.percentile(op, 99) - np.percentile(op, 1)) / 2
                met = []
                starts = op[0] + np.linspace(-valve.fs, valve.fs, 81)
                for replay in he_replays(op, valve.fs, valve.fd, starts):
                    same = np.abs(replay - mv) < 1e-9
                    if same.any() and same[int(np.argmax(same)):].all():
                        met.append(int(np.argmax(same)))
                rows[i].append((half_range / valve.S, len(met) / 81,
                                float(np.median(met)) if met else float("nan")))
    for i, values in rows.items():
        ratio, share, when = (np.array(v) for v in zip(*values, strict=True))
        print(f"  valve {i}: OP half-range / S {np.median(ratio):.2f} (median of {len(values)}); "
              f"replay meets the MV from {np.mean(share):.0%} of starting positions "
              f"(none in {np.mean(share == 0):.0%} of cases), after "
              f"{np.nanmedian(when) if np.isfinite(when).any() else float('nan'):.0f} samples "
              f"(median) of {int(np.sum(run.t >= 2000.0))}")
    print()


REPLAY_HARMONICS = (1, 3, 5, 7)


def impulse_response(entry: DiscreteEntry, length: int) -> np.ndarray:
    """The first ``length`` samples of a sampled entry's response to a unit pulse."""
    state, h = np.zeros(entry.Ad.shape[0]), np.zeros(length)
    d = entry.delay_samples
    for k in range(length):
        now, before = float(k == d), float(k == d + 1)
        h[k] = entry.C @ state + entry.D * before
        state = entry.Ad @ state + entry.B0 * now + entry.B1 * before
    return h


def replay_weights(process: ProcessMatrix, samples: int, ts: float, period_s: float
                   ) -> tuple[np.ndarray, slice]:
    """``q[i, k, h]``: the phasor at harmonic ``h`` of ``G_ik`` driven by ``u``, over a window
    of whole periods after 300 s (or a period) of warm-up, is ``q[i, k, h] @ u`` (the sampled
    model's impulse response correlated with the phasor's basis; exact for the simulator)."""
    warm = round(max(period_s, 300.0) / ts)
    whole = round((samples - warm) * ts // period_s * period_s / ts)
    t = np.arange(whole) * ts
    basis = np.exp(-2j * np.pi * np.outer(REPLAY_HARMONICS, t) / period_s) * 2 / whole
    n = len(process)
    q = np.zeros((n, n, len(REPLAY_HARMONICS), samples), complex)
    for i, row in enumerate(process):
        for k, g in enumerate(row):
            if g is None:
                continue
            h = impulse_response(discretise(g, ts), warm)
            for m, b in enumerate(basis):
                full = np.zeros(samples, complex)
                full[warm:warm + whole] = b
                q[i, k, m] = fftconvolve(full[::-1], h)[:samples][::-1]
    return q, slice(warm, warm + whole)


def ridge_misfit(y: np.ndarray, weight: np.ndarray, regs: np.ndarray, sigma: float | None
                 ) -> float:
    """``min |w (y - sum_k (1 + e_k) z_k)|^2 + sum_k e_k^2 / sigma^2`` over real gain errors
    ``e_k`` of one PV's row (``regs[k]`` the phasors ``z_k`` of ``G_ik u_k``); no ``e`` when
    ``sigma`` is None."""
    r, z = weight * (y - regs.sum(axis=0)), regs * weight
    if sigma is None:
        return float(np.sum(np.abs(r) ** 2))
    a = np.real(np.conj(z) @ z.T) + np.eye(len(regs)) / sigma**2
    b = np.real(np.conj(z) @ r)
    return float(np.sum(np.abs(r) ** 2) - b @ np.linalg.solve(a, b))


def oracle_replay() -> None:
    """Would a replay of the sticky valves see valve 3 beside another, if each valve's
    S, J and stick state were found?  On the calibration seeds, each sticky valve replayed
    from its OP with its true fs and fd, its starting position chosen (of 201 over
    [-fs, fs], by coordinate descent from the middle) to fit the PV phasors at harmonics
    1, 3, 5, 7 (through the sampled model,
    each matrix gain free within sigma = 20 %, or exact); the misfit of the true set and of
    the set without its last valve (healthy), in units of 2 % of each PV phasor."""
    print("== oracle: the replayed set with and without its last valve (calibration seeds) ==")
    for seed in CALIBRATION_SEEDS[:2]:
        for sticky in ((1, 2), (1, 3), (2, 3), (1, 2, 3)):
            model, _ = randomised_column(sticky, seed)
            run = model.run()
            late = run.t >= 2000.0
            op = [x - x.mean() for x in run.op[:, late]]
            pv = list(run.pv[:, late])
            period = measure_fingerprint(op, pv, 0.5).period_s
            replays = {}
            for i in sticky:
                valve = model.loops[i - 1].valve
                assert isinstance(valve, HeValve)
                replays[i - 1] = he_replays(op[i - 1], valve.fs, valve.fd,
                                            op[i - 1][0] + np.linspace(-valve.fs, valve.fs, 201))
            line = []
            for label, error, sigma in (("exact", 0.0, 0.2), ("20 % off", 0.2, 0.2),
                                        ("20 % off, gains fixed", 0.2, None)):
                um = unit_model(model, gain_error=error, seed=seed)
                q, window = replay_weights(um.process, op[0].size, 0.5, period)
                length = window.stop - window.start
                basis = np.exp(-2j * np.pi * np.outer(REPLAY_HARMONICS, np.arange(length) * 0.5)
                               / period) * 2 / length
                y = np.array([basis @ (p[window] - p[window].mean()) for p in pv])
                noise = np.array([np.diff(p).std() for p in pv]) * 2 / np.sqrt(2 * length)
                weight = 1.0 / (0.02 * np.abs(y) + noise[:, None])
                tables = {k: np.einsum("ihs,ps->pih", q[:, k], u) for k, u in replays.items()}
                healthy = np.einsum("ikhs,ks->kih", q, np.array(op))

                def misfit(chosen: dict[int, int], q_: np.ndarray = healthy,
                           t_: dict[int, np.ndarray] = tables, w_: np.ndarray = weight,
                           y_: np.ndarray = y, s_: float | None = sigma) -> float:
                    return sum(ridge_misfit(y_[i], w_[i], np.array(
                        [t_[k][chosen[k], i] if k in chosen else q_[k, i] for k in range(3)]), s_)
                        for i in range(3))

                def fit(members: list[int]) -> float:
                    chosen = {k: 100 for k in members}
                    for _ in range(3):
                        for k in members:
                            chosen[k] = min(range(201),
                                            key=lambda at, k=k: misfit({**chosen, k: at}))
                    return misfit(chosen)

                members = [i - 1 for i in sticky]
                line.append(f"{label}: {fit(members):.1f} against {fit(members[:-1]):.1f}")
            print(f"  seed {seed} sticky {','.join(map(str, sticky)):6s} without valve "
                  f"{sticky[-1]}: " + "; ".join(line), flush=True)
    print()


REPLAY_PENALTIES = (0.0, 25.0, 50.0, 100.0, 200.0, 400.0, 800.0, 1600.0)
"""Penalties per sticky valve the replay study tries on the calibration seeds."""


def replay_study(seeds: tuple[int, ...], calibration: bool) -> None:
    """The time-domain replay (issue 22, :mod:`analytics.plantwide.replay`): every non-empty
    sticky set of the column with S and J within 30 % of Table 2.3 on ``seeds``, exact and
    20 % wrong gains; the right set named per sticky set, the named valves' S, the external
    sines and the healthy column, and the time of one localisation.  On the calibration
    seeds (``plantwide.py replay``) every penalty of :data:`REPLAY_PENALTIES` is scored
    (the constant is chosen there); on the held-out seeds (``plantwide.py replay
    held-out``) only the module's :data:`~analytics.plantwide.REPLAY_PENALTY`."""
    print(f"== time-domain replay of every sticky set, seeds {seeds[0]}-{seeds[-1]} "
          f"({'calibration' if calibration else 'held out'}) ==")
    penalties = REPLAY_PENALTIES if calibration else (REPLAY_PENALTY,)
    cases, times = [], []
    warm_up, _ = randomised_column(STICKY_SETS[0], seeds[0])  # the JIT compiled, untimed
    replay_sticky_sets(column_unit(warm_up), 0.5, unit_model(warm_up).process)
    for seed in seeds:
        for sticky in STICKY_SETS:
            model, true_s = randomised_column(sticky, seed)
            unit = column_unit(model)
            for error in (0.0, 0.2):
                um = unit_model(model, gain_error=error, seed=seed)
                start = time.perf_counter()
                found = replay_sticky_sets(unit, 0.5, um.process)
                times.append(time.perf_counter() - start)
                cases.append((sticky, error, true_s, found))
            print(f"  seed {seed} sticky {','.join(map(str, sticky)):6s} best "
                  + ", ".join(f"{{{','.join(v.removeprefix('loop') for v in f.loops)}}} "
                              f"{f.misfit:.0f}" for f in cases[-1][3].candidates[:3])
                  + f" (healthy {cases[-1][3].no_valve_misfit:.0f}); "
                  f"{times[-2]:.2f} s, {times[-1]:.2f} s with gains 20 % off", flush=True)

    def named(found: ReplayLocalisation, penalty: float) -> tuple[str, ...]:
        m = found.samples
        scores = [(m * np.log(found.no_valve_misfit / m), ())] + [
            (m * np.log(f.misfit / m) + penalty * len(f.loops), f.loops)
            for f in found.candidates]
        return min(scores, key=lambda pair: pair[0])[1]

    for penalty in penalties:
        line = []
        for label, error in (("exact", 0.0), ("gains 20 % off", 0.2)):
            right = {s: 0 for s in STICKY_SETS}
            for sticky, e, _, found in cases:
                if e == error:
                    right[sticky] += set(named(found, penalty)) == {f"loop{i}" for i in sticky}
            total = sum(right.values())
            line.append(f"{label} {total}/{len(seeds) * len(STICKY_SETS)} ("
                        + ", ".join(f"{{{','.join(map(str, s))}}} {right[s]}"
                                    for s in STICKY_SETS) + ")")
        print(f"penalty {penalty:6.0f}: " + "; ".join(line))
    errors = []
    for _, error, true_s, found in cases:
        if error == 0.0 and set(named(found, REPLAY_PENALTY)) == set(true_s):
            fit = found.fit_of(tuple(true_s))
            assert fit is not None
            errors += [s / true_s[v] - 1 for v, s in zip(fit.loops, fit.S, strict=True)]
    if errors:
        e = np.abs(errors)
        print(f"S of the named valves (right sets, exact gains, penalty "
              f"{REPLAY_PENALTY:g}): median error {np.median(e):.0%}, "
              f"{np.mean(e <= 0.25):.0%} within 25 % ({len(e)} valves)")
    print(f"localisation time over all {len(times)} localisations (one core): median "
          f"{statistics.median(times):.2f} s, max {max(times):.2f} s")
    for label, unit, um in healthy_columns():
        found = replay_sticky_sets(unit, 0.5, um.process)
        print(f"  {label}: named "
              + "; ".join(f"penalty {p:g} {','.join(named(found, p)) or '-'}"
                          for p in penalties)
              + f" (healthy misfit {found.no_valve_misfit:.0f} over {found.samples}, "
              f"best {found.candidates[0].misfit:.0f})")
    print()


def tep_unit(name: str) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], dict[str, np.ndarray]]:
    data = np.loadtxt(TEP / name)
    if data.shape[0] == 52:
        data = data.T
    if name.endswith("_te.dat"):
        data = data[160:]
    loops = {f"XMV({j})": (data[:, 40 + j], data[:, pv - 1]) for j, pv in TEP_PV_OF.items()}
    others = {f"XMEAS({i})": data[:, i - 1] for i in range(1, 42) if i not in TEP_PV_OF.values()}
    return loops, others


def tennessee_eastman() -> None:
    print("== Tennessee Eastman (Braatz data, 3-minute samples, test runs from the fault on) ==")
    if not TEP.is_dir():
        print(f"skipped: {TEP} not found\n")
        return
    truth = {"d00": "none", "d14": "XMV(10)", "d15": "XMV(11)"}
    for name in ("d00.dat", "d00_te.dat", "d14.dat", "d14_te.dat", "d15.dat", "d15_te.dat"):
        loops, others = tep_unit(name)
        result = diagnose_unit(loops, 180.0, measurements=others)
        named = ", ".join(f"{f.loop} ({f.confidence:.2f})" for f in result.sticky_valves)
        print(f"{name:11s} sticky: {truth[name[:3]]:8s} named: {named or 'none'}")
        for group in result.groups:
            print(f"     {group.period_s / 180.0:6.1f} samples, {group.cycles:5.1f} cycles: "
                  f"{group.note[:110]}")
    print()


def speed() -> None:
    print("== speed (median of repeated runs, one core) ==")
    rng = np.random.default_rng(2)
    signals = []
    for i in range(8):  # a valve slipping every 22-28 samples, seen through a lag, in noise
        halves = rng.integers(22, 29, 120)
        mv = np.concatenate([np.full(h, (-1.0) ** j) for j, h in enumerate(halves)])[:2000]
        signals.append(lfilter([0.1], [1, -0.9 + 0.02 * i], mv)
                       + 0.05 * rng.standard_normal(2000))

    def surrogates() -> None:
        for x in signals:
            surrogate_nonlinearity_index(x, 50.0, surrogates=50)

    def surrogates_all_cycles() -> None:
        for x in signals:
            surrogate_nonlinearity_index(x, 50.0, surrogates=50, max_cycles=40)

    surrogates()  # compile
    print(f"surrogate index, 8 signals x 2000 samples, M = 50, K = 8, S_n = 30 "
          f"(latest 12 cycles, the default): {median_time(surrogates, 7):.3f} s")
    print(f"the same on all 40 cycles of each signal: "
          f"{median_time(surrogates_all_cycles, 7):.3f} s")
    if TEP.is_dir():
        loops, others = tep_unit("d14.dat")
        flat = {f"{role}_{loop}": x for loop, pair in loops.items()
                for role, x in zip(("op", "pv"), pair, strict=True)} | others
        print(f"plant-wide grouping, 52 TEP signals x 480 samples: "
              f"{median_time(lambda: find_oscillation_groups(flat, 180.0), 5):.3f} s")
    unit = column_unit(column3x3(sticky=(1, 2)))
    print(f"whole unit diagnosis, column with valves 1 and 2 sticky (3 loops x 12000 samples): "
          f"{median_time(lambda: diagnose_unit(unit, 0.5), 3):.2f} s")


if __name__ == "__main__":
    if sys.argv[1:] == ["model"]:
        model_localisation()
        sys.exit()
    if sys.argv[1:2] == ["score"]:
        score_sets(SCORED_SEEDS if sys.argv[2:] == ["held-out"] else CALIBRATION_SEEDS)
        sys.exit()
    if sys.argv[1:2] == ["replay"]:
        held_out = sys.argv[2:] == ["held-out"]
        replay_study(SCORED_SEEDS if held_out else CALIBRATION_SEEDS, not held_out)
        sys.exit()
    if sys.argv[1:] == ["oracle"]:
        oracle_replay()
        sys.exit()
    if sys.argv[1:] == ["sync"]:
        replay_sync()
        sys.exit()
    if sys.argv[1:] == ["why"]:
        confusion()
        sys.exit()
    column()
    tennessee_eastman()
    model_localisation()
    speed()
