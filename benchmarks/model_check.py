"""Model check (issues 8 and 21): accuracy on hidden effects, confidence, real loops, speed.

Prints, in one run, for the two case generators side by side, the first
(analytics.model_check.cases, which the check was developed on) and the
independent one (analytics.model_check.cases_independent, held out):

1. per hidden effect (seeds 0..N-1, N = 10 or the first argument), how often
   the cause named is the hidden effect, the median held-out NMSE before and
   after extension, and what else was named; ``none`` cases too, and how
   often a second cause was named in a one-effect case;
2. two effects at once (N // 2 seeds per pair): how often both are named;
3. the reliability table: every cause named (first and second causes,
   ``none`` included) binned by its confidence, against how often it was right;
4. what the check finds on real loops with an identified model (plant_dev
   windows and the ISDB loops of ../shared/data): held-out NMSE of the base
   model, cause, confidence and runner-up; a cause named with confidence
   >= 0.9 while the base model explains under half the data is flagged;
5. the time of a check of 6,000 samples, per effect and for two-effect
   cases, on one core (BLAS threads pinned to 1 before numpy loads): CPU
   time, as the machine may be shared, with the wall time [target < 2 s].

Run with ``.venv/bin/python benchmarks/model_check.py [N] [SECTION]``,
SECTION one of ``cases``, ``real``, ``speed`` (default: all).
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_name] = "1"

import csv  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from collections.abc import Callable  # noqa: E402
from itertools import pairwise  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from analytics.model_check import ModelCheck, check_model  # noqa: E402
from analytics.model_check.cases import CATALOGUE, HiddenEffectCase, hidden_effect_case  # noqa: E402
from analytics.model_check.cases_independent import independent_case  # noqa: E402
from analytics.model_check.model import PROCESS_JSON_TYPES  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
SAMPLES = 6000
REPEATS = 3
CONFIDENT = 0.9
BINS = (0.0, 0.3, 0.5, 0.7, 0.9, 1.0001)
PAIRS = (
    ("asymmetric_stiction", "external_disturbance"),
    ("gain_mismatch", "measurement_quantization"),
    ("valve_characteristic", "external_disturbance"),
    ("deadtime_mismatch", "measurement_quantization"),
)
GENERATORS: dict[str, Callable[..., HiddenEffectCase]] = {
    "first (tuned on)": hidden_effect_case,
    "independent (held out)": independent_case,
}


def _check(case: HiddenEffectCase) -> ModelCheck:
    return check_model(case.op, case.pv, case.ts, sp=case.sp, model=case.base_model)


def hidden_effects(name: str, generator: Callable[..., HiddenEffectCase], seeds: int) -> None:
    """Sections 1-3 for one generator."""
    print(f"\n=== generator: {name}; {seeds} loops per effect, {SAMPLES} samples each")
    print(f"{'hidden effect':30s} {'named':>7s}  {'NMSE before':>11s} {'after':>9s}  confusions")
    findings: list[tuple[float, bool]] = []
    named_total = effects_total = seconds = 0
    rates = {}
    for effect in CATALOGUE:
        named: Counter[str] = Counter()
        before, after = [], []
        for seed in range(seeds):
            result = _check(generator(effect, seed, SAMPLES))
            named[result.cause.effect] += 1
            before.append(result.gain.nmse_before)
            after.append(result.gain.nmse_after)
            for i, cause in enumerate(result.causes):
                findings.append((cause.confidence, i == 0 and cause.effect == effect))
            seconds += len(result.causes) > 1
        rates[effect] = named[effect] / seeds
        if effect != "none":
            named_total += named[effect]
            effects_total += seeds
        wrong = ", ".join(f"{k} x{v}" for k, v in named.items() if k != effect)
        print(
            f"{effect:30s} {named[effect]:3d}/{seeds:<3d}  {statistics.median(before):11.3g} "
            f"{statistics.median(after):9.3g}  {wrong}"
        )
    worst = min((r, e) for e, r in rates.items() if e != "none")
    print(
        f"effects named: {named_total}/{effects_total} = {100 * named_total / effects_total:.0f} % "
        f"[>= 90 %]; lowest class {worst[1]} {100 * worst[0]:.0f} % [>= 80 %]; none "
        f"{100 * rates['none']:.0f} % [>= 90 %]; one-effect cases with a second cause named: "
        f"{seconds}/{len(CATALOGUE) * seeds}"
    )
    both_total = 0
    pair_seeds = max(seeds // 2, 1)
    print(f"two effects at once ({pair_seeds} loops per pair): both named / first / second")
    for pair in PAIRS:
        both = first = second = 0
        for seed in range(pair_seeds):
            result = _check(generator(pair, seed, SAMPLES))
            found = [c.effect for c in result.causes]
            both += set(pair) <= set(found)
            first += pair[0] in found
            second += pair[1] in found
            for cause in result.causes:
                findings.append((cause.confidence, cause.effect in pair))
        both_total += both
        print(f"  {' + '.join(pair):52s} {both}/{pair_seeds}  {first}/{pair_seeds}  "
              f"{second}/{pair_seeds}")
    total = len(PAIRS) * pair_seeds
    print(f"both effects named: {both_total}/{total} = {100 * both_total / total:.0f} % [>= 70 %]")
    print("reliability: causes named (first and second, none included) by confidence")
    print(f"  {'confidence':>12s} {'findings':>8s} {'right':>6s}")
    confidences = np.array([c for c, _ in findings])
    right = np.array([r for _, r in findings])
    for low, high in pairwise(BINS):
        inside = (confidences >= low) & (confidences < high)
        share = f"{100 * right[inside].mean():5.0f} %" if inside.any() else "     -"
        print(f"  {low:4.2f}-{min(high, 1.0):4.2f}  {int(inside.sum()):8d} {share}")
    confident = confidences >= CONFIDENT
    if confident.any():
        print(f"  confidence >= {CONFIDENT}: {100 * right[confident].mean():.1f} % right "
              f"of {int(confident.sum())} [>= 95 %]")


def _plant_dev() -> list[tuple[str, str, float, np.ndarray, np.ndarray, np.ndarray]]:
    labels = DATA / "plant_dev" / "labels.csv"
    if not labels.is_file():
        return []
    with labels.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    loops = []
    for row in rows:
        table = np.genfromtxt(DATA / "plant_dev" / f"{row['window']}.csv", delimiter=",",
                              names=True)
        loops.append((row["window"], row["label"], float(row["ts_s"]), table["op"], table["pv"],
                      table["sp"]))
    return loops


def _isdb() -> list[tuple[str, str, float, np.ndarray, np.ndarray, None]]:
    labels = DATA / "isdb14" / "labels.csv"
    if not labels.is_file():
        return []
    loops = []
    with labels.open(newline="") as handle:
        for row in csv.DictReader(handle):
            table = np.genfromtxt(DATA / "isdb14" / f"{row['loop']}.csv", delimiter=",", names=True)
            loops.append((row["loop"], row["label"], float(row["ts_s"]), table["OP"], table["PV"],
                          None))
    return loops


def real_loops() -> None:
    print("\nreal loops (no model given: identified first; plant_dev with its SP)")
    loops = [*_plant_dev(), *_isdb()]
    if not loops:
        print("  ../shared/data not found: skipped")
        return
    print(f"{'loop':12s} {'label':11s} {'n':>5s} {'NMSE base':>9s} {'after':>7s}  "
          f"{'cause':28s} conf  runner-up")
    flagged = 0
    for name, label, ts, op, pv, sp in loops:
        try:
            result = check_model(op, pv, ts, sp=sp)
        except Exception as exc:  # a benchmark reports a refusal and goes on
            print(f"{name:12s} {label:11s} refused: {exc}")
            continue
        flag = result.nmse_base_test > 0.5 and result.cause.confidence >= CONFIDENT
        flagged += flag
        causes = " + ".join(c.effect for c in result.causes)
        print(
            f"{name:12s} {label:11s} {op.size:5d} {result.nmse_base_test:9.3g} "
            f"{result.gain.nmse_after:7.3g}  {causes:28s} {result.cause.confidence:4.2f}  "
            f"{result.cause.runner_up or '-'}{'  CONFIDENT ON A MODEL THAT EXPLAINS LITTLE' * flag}"
        )
    print(f"confident causes on base models with held-out NMSE > 0.5: {flagged} [target 0]")


def speed(seeds: int) -> None:
    """CPU time of one check (the machine may be shared: wall time is shown as well)."""
    print(f"\nspeed: one check of {SAMPLES} samples, median of {REPEATS} after a warm-up; "
          "CPU time of the one core (wall time in brackets)")
    cpu_all = []
    for name, generator in GENERATORS.items():
        for effect in (*CATALOGUE, *PAIRS[: max(seeds // 5, 1)]):
            case = generator(effect, 0, SAMPLES)
            _check(case)
            cpu, wall = [], []
            for _ in range(REPEATS):
                start, start_wall = time.process_time(), time.perf_counter()
                _check(case)
                cpu.append(time.process_time() - start)
                wall.append(time.perf_counter() - start_wall)
            cpu_all.extend(cpu)
            label = effect if isinstance(effect, str) else " + ".join(e[:12] for e in effect)
            kind = PROCESS_JSON_TYPES[case.base_model.process.kind]
            print(f"{name[:11]:11s} {label:28s} ({kind:11s}) "
                  f"{statistics.median(cpu):6.2f} s  ({statistics.median(wall):.2f} s)")
    print(f"{'all':53s} median {statistics.median(cpu_all):6.2f} s, max {max(cpu_all):.2f} s  "
          f"[target < 2 s: {'met' if max(cpu_all) < 2 else 'MISSED'}]")


def main() -> None:
    seeds = int(sys.argv[1]) if len(sys.argv) > 1 else 10
    section = sys.argv[2] if len(sys.argv) > 2 else "all"
    if section in ("all", "cases"):
        for name, generator in GENERATORS.items():
            hidden_effects(name, generator, seeds)
    if section in ("all", "real"):
        real_loops()
    if section in ("all", "speed"):
        speed(seeds)


if __name__ == "__main__":
    main()
