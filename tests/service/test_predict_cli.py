"""``loopwatch predict`` and ``loopwatch compensate`` (service.commands.predict and
.compensate), run through a parser built here with each module's ``register``.

The predicted cycle is checked against the harmonic balance computed here from
the transfer function and the closed-form describing function, and against the
simulated temperature loop of thesis section 5.5.1 (35.0 s, as in
tests/analytics/test_limit_cycle.py).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from analytics.compensation import compare_compensators
from analytics.describing import choudhury_df
from analytics.lti import TransferFunction
from service.commands import CliError, compensate, predict

TEMPERATURE = {
    "dt": 1.0,
    "process": {"type": "fopdt", "K": 0.4346, "tau": 27.58, "theta": 6.0},
    "controllers": [{"Kc": 10, "Ti": 10}],
    "valves": [{"model": "choudhury", "S": 4, "J": 2}],
}
TWO_BY_TWO = {
    "dt": 0.2,
    "process": {
        "matrix": [
            [{"type": "fopdt", "K": 1.0, "tau": 10, "theta": 2}, None],
            [
                {"num": [0.2], "den": [12, 1], "theta": 4},
                {"type": "fopdt", "K": 0.8, "tau": 6, "theta": 1},
            ],
        ]
    },
    "controllers": [{"Kc": 3.0, "Ti": 6.0}, {"Kp": 1.0, "Ki": 0.125}],
    "valves": [{"model": "choudhury", "S": 4, "J": 2}, None],
}


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(prog="loopwatch")
    commands = top.add_subparsers(dest="command", required=True)
    predict.register(commands)
    compensate.register(commands)
    return top


def run(argv: list[str]) -> int:
    args = parser().parse_args(argv)
    return int(args.handler(args))


def write(tmp_path: Path, spec: Any, name: str = "model.json") -> str:
    path = tmp_path / name
    path.write_text(spec if isinstance(spec, str) else json.dumps(spec))
    return str(path)


def test_predict_json_temperature_loop(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["predict", write(tmp_path, TEMPERATURE), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    (cycle,) = data["limit_cycles"]
    assert cycle["stable"] and cycle["period_s"] == pytest.approx(2 * math.pi / cycle["omega"])
    w, amplitude = cycle["omega"], cycle["amplitudes"][0]
    process = TransferFunction.fopdt(0.4346, 27.58, 6.0)
    loop = 10 * (1 - 1j / (10 * w)) * complex(process.frequency_response(w)) * np.exp(-0.5j * w)
    assert loop == pytest.approx(-1 / complex(choudhury_df(amplitude, 4, 2)), abs=1e-8)
    simulated = data["simulated"]
    assert simulated["oscillating"] and simulated["period_s"] == pytest.approx(35.0, rel=0.01)
    expected_error = 100 * (cycle["period_s"] - simulated["period_s"]) / simulated["period_s"]
    assert data["comparison"]["period_error_pct"] == pytest.approx(expected_error)
    # without a duration: 200 periods of the slowest predicted cycle, at least 2000 s
    assert data["simulated"]["window_s"][1] == pytest.approx(200 * cycle["period_s"], abs=1.0)


def test_predict_text_report(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["predict", write(tmp_path, {**TEMPERATURE, "duration": 1500})]) == 0
    out = capsys.readouterr().out
    assert "sticky valves: loop1" in out
    assert "Choudhury DF with S=4, J=2" in out
    assert "36.41" in out and "yes" in out  # the predicted period, stable
    assert "simulation, analysed 750-1500 s: oscillates" in out
    assert "describing function against the simulation: period +4.0 %" in out


def test_predict_multi_loop_with_a_healthy_valve(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["predict", write(tmp_path, TWO_BY_TWO), "--json", "--omega-range", "0.05", "5"]
    assert run(argv) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["omega_range"] == [0.05, 5.0]
    stable = [c for c in data["limit_cycles"] if c["stable"]]
    assert stable and all(c["amplitudes"][1] is None for c in stable)  # healthy valve
    assert data["simulated"]["oscillating"]
    assert abs(data["comparison"]["period_error_pct"]) < 25.0


BAD_MODELS = {
    "non-square": (
        {**TWO_BY_TWO, "process": {"matrix": [[{"type": "integrating", "K": 1}, None, None]] * 2}},
        r"process.matrix must be square \(2 x 2, one row and column per loop\): "
        r"row 1 has 3 entries",
    ),
    "missing process parameter": (
        {
            **TWO_BY_TWO,
            "process": {
                "matrix": [
                    [{"type": "fopdt", "K": 1.0, "tau": 10}, None],
                    [None, {"type": "fopdt", "K": 0.8, "theta": 1}],
                ]
            },
        },
        r"process.matrix\[2\]\[2\]: missing key 'tau' for model type 'fopdt'",
    ),
    "missing diagonal": (
        {**TWO_BY_TWO, "process": {"matrix": [[{"type": "integrating", "K": 1}, None]] * 2}},
        r"process.matrix\[2\]\[2\] is null",
    ),
    "missing controller parameter": (
        {**TWO_BY_TWO, "controllers": [{"Kc": 3.0}, {"Ti": 8.0}]},
        r"controllers\[2\]: a controller needs 'Kc'",
    ),
    "missing valve parameter": (
        {**TEMPERATURE, "valves": [{"model": "choudhury", "S": 4}]},
        r"valves\[1\]: valve model 'choudhury'.*'J'",
    ),
    "one controller for two loops": (
        {**TWO_BY_TWO, "controllers": [{"Kc": 3.0}]},
        r"'controllers' must be a list with one entry per loop \(2\)",
    ),
    "no valves key": (
        {k: v for k, v in TEMPERATURE.items() if k != "valves"},
        "lacks the required key 'valves'",
    ),
    "unstable without stiction": (
        {**TEMPERATURE, "controllers": [{"Kc": 40, "Ti": 10}]},
        r"unstable without stiction, so no limit cycle: the loop is unstable with healthy "
        r"valves \(2 right-half-plane roots\)",
    ),
    "healthy valves only": ({**TEMPERATURE, "valves": [None]}, "no sticky valve"),
    "invalid JSON": ('{"dt": 1,', "invalid JSON at line 1, column 10"),
}


@pytest.mark.parametrize("case", sorted(BAD_MODELS))
def test_bad_models_are_refused_precisely(tmp_path: Path, case: str) -> None:
    spec, message = BAD_MODELS[case]
    path = write(tmp_path, spec)
    with pytest.raises(CliError, match=message) as error:
        run(["predict", path])
    assert str(error.value).startswith(path)


def test_missing_file_and_bad_duration(tmp_path: Path) -> None:
    with pytest.raises(CliError, match="no such file"):
        run(["predict", str(tmp_path / "absent.json")])
    with pytest.raises(CliError, match="--duration must be > 0"):
        run(["predict", write(tmp_path, TEMPERATURE), "--duration", "-5"])


def test_compensate_table_and_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["compensate", "--duration", "3000", "--no-sensitivity"]) == 0
    out = capsys.readouterr().out
    lines = [line.split()[0] for line in out.splitlines()[5:]]
    assert lines == ["none", "knocker", "constant", "model-based"]
    assert run(["compensate", "--duration", "3000", "--switch-on", "1000", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    expected = compare_compensators(duration=3000.0)
    assert [row["iae"] for row in data["comparison"]] == pytest.approx([r.iae for r in expected])
    assert len(data["sensitivity"]) == 13  # thesis Tables 4.2-4.4
    exact = data["sensitivity"][0]
    assert (exact["fs"], exact["fd"], exact["thesis_op_ss"]) == (3.0, 2.0, 53.0)
    assert data["sensitivity"][1]["thesis_op_ss"] == 52.99


def test_compensate_text_sensitivity(capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["compensate", "--duration", "2500", "--switch-on", "1000"]) == 0
    out = capsys.readouterr().out
    assert "thesis Tables 4.2-4.4" in out
    assert out.count("\n 3.00  2.00") == 9  # the exact case and the eight K errors


def test_compensate_refuses_an_empty_window() -> None:
    with pytest.raises(CliError, match="fewer than two samples"):
        run(["compensate", "--compensate-from", "3000", "--duration", "3000", "--no-sensitivity"])
