"""The ``loopwatch`` command line: simulate, demo, and analyze and model-check of plant exports."""

import argparse
import csv
import json
from pathlib import Path

import pytest

import service.commands
from service.cli import COMMANDS, main
from tests.shared_data import SHARED_DATA, require_file


def test_every_command_module_is_registered_once():
    package = Path(service.commands.__file__).parent
    modules = sorted(p.stem for p in package.glob("*.py") if p.stem != "__init__")
    assert sorted(module.__name__.rpartition(".")[2] for module in COMMANDS) == modules
    commands = argparse.ArgumentParser().add_subparsers()
    for module in COMMANDS:  # each adds one subcommand
        before = set(commands.choices)
        module.register(commands)
        assert len(set(commands.choices) - before) == 1, module.__name__


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


def _write_loop(tmp_path, case_name, samples=3000):
    from analytics.synthetic_cases import synthetic_library

    case = next(c for c in synthetic_library(samples) if c.name == case_name)
    result = case.simulate()
    path = tmp_path / f"{case_name}.csv"
    with path.open("w") as handle:
        handle.write("Time,OP,PV,SP\n")
        for row in zip(result.t, result.op[0], result.pv[0], result.sp[0], strict=True):
            handle.write(",".join(f"{v:.6g}" for v in row) + "\n")
    return path


def test_analyze_json_contract_on_a_sticky_loop(tmp_path, capsys):
    path = _write_loop(tmp_path, "flow-kano-S4-J2-ts1")
    assert main(["analyze", str(path), "--process-type", "self-regulating", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["samples"] == 3000 and report["ts"] == 1.0
    assert report["quality"]["usable"] is True
    osc = report["oscillation"]
    assert osc["detected"] is True and 80 < osc["period_s"] < 130
    assert {"regularity", "amplitude_op", "amplitude_pv"} <= osc.keys()
    stiction = report["stiction"]
    assert stiction["verdict"] == "stiction" and 0 < stiction["confidence"] <= 1
    assert set(stiction["methods"]) >= {"cross_correlation", "bicoherence", "surrogate"}
    assert all({"index", "decision"} <= m.keys() for m in stiction["methods"].values())
    q = report["quantification"]
    assert {"S", "J", "fs", "fd", "fit_r2"} <= q.keys()
    assert abs(q["S"] - 4.0) < 1.5  # the simulated valve: Kano S = 4 %, J = 2 %


def test_analyze_readable_report_of_a_healthy_loop(tmp_path, capsys):
    path = _write_loop(tmp_path, "flow-noise-ts1")
    assert main(["analyze", str(path)]) == 0
    out = capsys.readouterr().out
    assert "oscillation: none found" in out
    # Its valve hardly moved: too little to judge (issue 17), with the travel seen.
    assert "stiction: UNDECIDED" in out and "not enough valve movement to judge" in out


@pytest.mark.parametrize(
    ("text", "args", "message"),
    [
        ("t,op,pv\n0,1,2\n1,x,3\n", [], "row 3, column 'op': 'x' is not a number"),
        ("t,flow\n0,1\n1,2\n", [], "needs an 'op' or a 'pv' column"),
        ("op,pv\n1,2\n2,3\n", [], "no time column"),
        # the time as the file writes it: seconds since start are no 1970 date (QA)
        ("t,op,pv\n0,1,2\n5,1,2\n5,1,2\n", [], "rows 3 and 4: the same time '5'; remove"),
        ("t,op,pv\n2026-03-01T10:00:00Z,1,2\n2026-03-01T11:00:00+01:00,1,2\n", [],
         "rows 2 and 3: the same time '2026-03-01T10:00:00Z' and '2026-03-01T11:00:00+01:00'"),
        ("t,op,pv\n" + "".join(f"{k},{k % 7},{k % 5}\n" for k in range(20)), [],
         "20 data rows, at least 100 are needed"),
    ],
)
def test_analyze_refuses_bad_input_with_file_row_and_column(tmp_path, capsys, text, args, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    assert main(["analyze", str(path), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and "bad.csv" in err


# ---------------------------------------------------------------- the plant's own exports

PLANT = SHARED_DATA / "plant_unlabelled"


def test_analyze_reads_a_plant_export_as_it_is_and_warns_of_a_wrong_ts(capsys):
    """BOM, id/date/time columns, newest first, NULL cells: read as the replay reads them."""
    path = require_file(PLANT / "FIC-211_20241121-27.csv")
    assert main(["analyze", str(path), "--op", "FV_211", "--pv", "FT_211", "--ts", "5",
                 "--json"]) == 0
    out, err = capsys.readouterr()
    report = json.loads(out)
    assert report["samples"] == 10080 and report["ts"] == 60.0
    assert "93 NaN" in json.dumps(report["quality"])  # the NULL cells, kept as holes
    assert ("warning: --ts 5 s disagrees with the time column (date and time: median step "
            "60 s); the time column is used") in err


def test_model_check_reads_a_plant_export_in_semicolons_with_decimal_commas(tmp_path, capsys):
    """The same export as a European spreadsheet writes it gives the same model check."""
    source = require_file(PLANT / "LIC-106_20241121-27.csv")
    text = source.read_text(encoding="utf-8-sig")
    european = tmp_path / "LIC-106.csv"
    european.write_text("\ufeff" + text.replace(",", ";").replace(".", ","), encoding="utf-8")
    results = []
    for path in (source, european):
        assert main(["model-check", str(path), "--op", "LV_106", "--pv", "FT_115",
                     "--json"]) == 0
        results.append(json.loads(capsys.readouterr().out))
    assert results[0]["base_model"]["dt"] == 60.0
    assert results[0] == results[1]
