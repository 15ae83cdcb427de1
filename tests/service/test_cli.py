"""The ``loopwatch`` command line: simulate and demo."""

import csv
import json

import pytest

from service.cli import main


def test_simulate_a_scenario_to_csv(tmp_path, capsys):
    out = tmp_path / "ch4.csv"
    assert main(["simulate", "chapter4", "--duration", "200", "--out", str(out)]) == 0
    rows = list(csv.reader(out.read_text().splitlines()))
    assert rows[0] == ["time", "sp", "op", "mv", "pv"]
    assert len(rows) == 1 + 201
    assert float(rows[-1][0]) == 200.0
    assert "wrote 201 samples of 1 loop(s)" in capsys.readouterr().err


def test_simulate_a_json_model_to_stdout(tmp_path, capsys):
    model = tmp_path / "model.json"
    model.write_text(
        json.dumps(
            {
                "dt": 1.0,
                "duration": 5,
                "process": {
                    "matrix": [
                        [{"type": "fopdt", "K": 1, "tau": 5}, None],
                        [None, {"type": "integrating", "K": 0.1, "theta": 1}],
                    ]
                },
                "controllers": [{"Kc": 1, "Ti": 10}, {"Kp": 0.5}],
                "valves": [None, {"model": "kano", "S": 2, "J": 1}],
                "names": ["FIC1", "LIC2"],
            }
        )
    )
    assert main(["simulate", str(model)]) == 0
    header = capsys.readouterr().out.splitlines()[0]
    assert header == "time,sp_FIC1,op_FIC1,mv_FIC1,pv_FIC1,sp_LIC2,op_LIC2,mv_LIC2,pv_LIC2"


def test_list_names_every_scenario(capsys):
    assert main(["simulate", "--list"]) == 0
    out = capsys.readouterr().out
    assert "chapter4" in out and "column-3" in out


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('{"dt": 1,', "invalid JSON at line 1, column 10"),
        ('{"dt": 1, "process": {"type": "fopdt", "K": 1, "tau": -1}}', "tau"),
        ('{"process": {"type": "fopdt", "K": 1, "tau": 1}}', "lacks the required key 'dt'"),
    ],
)
def test_bad_model_files_say_what_is_wrong(tmp_path, capsys, content, message):
    model = tmp_path / "bad.json"
    model.write_text(content)
    assert main(["simulate", str(model)]) == 2
    err = capsys.readouterr().err
    assert str(model) in err and message in err


def test_unknown_scenario(capsys):
    assert main(["simulate", "nonsense"]) == 2
    assert "neither a scenario name" in capsys.readouterr().err
