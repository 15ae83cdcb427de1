"""Stiction sizes of the demo's sticky valves, window by window, as the service sees them.

The demo (``loopwatch serve``) back-fills two hours of :mod:`connectors.plant_sim`
and analyses hour-long windows; the history rounds' windows that do not overlap
are the first two hours of the simulation.  This script takes the same simulated OP and
PV of FV-101 (Kano S 4, J 2), FV-105 (He S 8, J 4) and FV-502 (He S 4, J 2,
in the 3x3 column), scales them to % of span with the plant configuration's
ranges (:func:`service.analysis.to_percent_of_span`), and quantifies each
hour with the configured process type and without one
(:func:`analytics.quantification.quantify_stiction`), then combines the
hours (:func:`analytics.quantification.combine_windows`), as
``service.verdicts.settle_run`` does (issue 19).

Each window also prints the identified process gain K and the product K J.
FV-105 and FV-502 are He valves whose OP travels only 8 % and 6 % more per
cycle than S (8.67 vs 8, 4.26 vs 4): each valve slips once per OP reversal,
so MV is a square wave of height J, the slip times give S, and the PV steps
give only K J.  At the simulated S the output error varies by less than 3 %
(FV-105, J 3-7) and 0.4 % (FV-502 second hour, J 0.5-4) over J: J and K are
not separately identified from such a cycle, and the windows split the same
K J differently (FV-502: K -4.02, J 0.71 and K -0.72, J 4.18, K J -2.9 and
-3.0).  FV-105's square wave is fitted as well by a Kano valve that slips
less and then follows OP (first hour: S 6.96, R^2 0.9934) as by a He valve
(S 8.01, J 5.97, K 0.77, R^2 0.9929): the family, and with it S, is not
decided by the fit either.

Run with ``.venv/bin/python benchmarks/demo_sizes.py [hours]`` (default 2).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from analytics.quantification import combine_windows, quantify_stiction  # noqa: E402
from connectors.plant_sim import PlantSimulator  # noqa: E402
from service.analysis import to_percent_of_span  # noqa: E402
from service.demo import LIVE_HORIZON_S  # noqa: E402

SIMULATED = {"FIC-101": (4.0, 2.0), "FIC-105": (8.0, 4.0), "AIC-502": (4.0, 2.0)}
"""The sticky loops of the demo and their valves' simulated S and J, % of span."""
WINDOW_S = 3600.0


def main(hours: int) -> None:
    # simulated as the demo simulates it: the history, then the live horizon
    plant = PlantSimulator(modbus_port=None, origin=0.0,
                           horizon_s=hours * WINDOW_S + LIVE_HORIZON_S)
    loops = {loop["id"]: loop for loop in plant.plant_config()["loops"]}
    for loop_id, (S, J) in SIMULATED.items():
        loop = loops[loop_id]
        ts = plant.sample_interval(loop_id)
        n = round(WINDOW_S / ts)
        signals = {}
        for name in ("op", "pv"):
            raw = np.array([plant.value(f"{loop_id}.{name.upper()}", i) for i in range(hours * n)])
            scaled = to_percent_of_span(raw, tuple(loop["ranges"][name]))
            assert scaled is not None
            signals[name] = scaled
        print(f"{loop_id}: simulated S {S:g}, J {J:g}; ts {ts:g} s, "
              f"process type {loop['process_type']}")
        sizes: dict[str, list[float]] = {"S": [], "J": []}
        intervals: dict[str, list[tuple[float, float]]] = {"S": [], "J": []}
        for hour in range(hours):
            part = slice(hour * n, (hour + 1) * n)
            op, pv = signals["op"][part], signals["pv"][part]
            for process_type in (loop["process_type"], None):
                est = quantify_stiction(op, pv, ts, process_type=process_type)
                if (est.S is None or est.J is None or est.search is None or est.model is None
                        or est.S_interval is None or est.J_interval is None):
                    print(f"  hour {hour}: {est.issues}")
                    continue
                (s_lo, s_hi), (j_lo, j_hi) = est.S_interval, est.J_interval
                print(f"  hour {hour} {process_type or 'either type':16s} S {est.S:5.2f} "
                      f"[{s_lo:.2f}, {s_hi:.2f}]  J {est.J:5.2f} [{j_lo:.2f}, {j_hi:.2f}]  "
                      f"{est.search.valve_model:4s} R^2 {est.fit_r2:.3f}  "
                      f"K {est.model.K:.3g}, K J {est.model.K * est.J:.3g}")
                if process_type is not None:
                    sizes["S"].append(est.S)
                    sizes["J"].append(est.J)
                    intervals["S"].append(est.S_interval)
                    intervals["J"].append(est.J_interval)
        if sizes["S"]:
            stick = combine_windows(sizes["S"], intervals["S"])
            slip = combine_windows(sizes["J"], intervals["J"])
            print(f"  combined S {stick.value:.2f} ({stick.value / S - 1:+.0%}), "
                  f"J {slip.value:.2f} ({slip.value / J - 1:+.0%})")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 2)
