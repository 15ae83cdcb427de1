"""``loopwatch unit-analyze``: the sticky valves of a unit from one CSV file."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from analytics.scenarios import column3x3
from service.cli import main
from service.commands import CliError, unit_analyze


def parser() -> argparse.ArgumentParser:
    """A ``loopwatch`` parser with only this command (the CLI registers it the same way)."""
    root = argparse.ArgumentParser(prog="loopwatch")
    unit_analyze.register(root.add_subparsers(dest="command", required=True))
    return root


def run(*argv: str) -> int:
    args = parser().parse_args(["unit-analyze", *argv])
    return int(args.handler(args))


@pytest.fixture(scope="module")
def column_csv(tmp_path_factory) -> str:
    """The simulated column with sticky valve 2, written by ``loopwatch simulate``."""
    path = tmp_path_factory.mktemp("unit") / "column.csv"
    assert main(["simulate", "column-2", "--out", str(path)]) == 0  # valves 1 and 2 sticky
    return str(path)


@pytest.mark.slow
def test_json_report_names_the_sticky_valves(column_csv, capsys):
    # The first 2000 s hold the start-up transient of the setpoint steps.
    assert run(column_csv, "--loops", "loop1,loop2,loop3", "--skip", "2000", "--json") == 0
    report = json.loads(capsys.readouterr().out)
    assert report["loops"] == ["loop1", "loop2", "loop3"]
    assert report["ts"] == 0.5 and report["samples"] == 12001
    assert report["k"] == 2
    assert {v["loop"] for v in report["sticky_valves"]} == {"loop1", "loop2"}
    assert all(0 < v["confidence"] <= 1 and v["S"] > 0 for v in report["sticky_valves"])
    periods = sorted(round(g["period_s"]) for g in report["groups"])
    assert len(periods) == 2 and 110 < periods[0] < 140 and 270 < periods[1] < 320


@pytest.mark.slow
def test_a_semicolon_file_with_decimal_commas_finds_its_loops_and_the_same_valves(
        column_csv, tmp_path, capsys):
    text = Path(column_csv).read_text()
    european = tmp_path / "column-2-eu.csv"
    european.write_text("\ufeff" + text.replace(",", ";").replace(".", ","), encoding="utf-8")
    reports = []
    for path in (column_csv, str(european)):
        assert run(path, "--skip", "2000", "--json") == 0  # the loops read off the header
        reports.append(json.loads(capsys.readouterr().out))
    assert reports[1]["loops"] == ["loop1", "loop2", "loop3"]
    assert reports[1]["sticky_valves"] == reports[0]["sticky_valves"]


@pytest.mark.slow
def test_readable_report_shows_groups_shapes_ranking_and_valves(column_csv, capsys):
    assert run(column_csv, "--skip", "2000") == 0  # every op_/pv_ pair of the file
    out = capsys.readouterr().out
    assert "3 loops (loop1, loop2, loop3), 12001 samples at 0.5 s" in out
    assert "sticky valves: k = 2" in out
    assert "shapes (thesis step 2): k = " in out
    assert "nonlinearity ranking (thesis step 3): " in out
    assert out.count("STICKY") == 2


def test_missing_values_are_refused_with_column_and_row(tmp_path):
    path = tmp_path / "gap.csv"
    rows = ["time,op_a,pv_a"] + [f"{k},{k % 7},{k % 5}" for k in range(100)]
    rows[51] = "50,3,"
    path.write_text("\n".join(rows) + "\n")
    message = "column 'pv_a': 1 missing value\\(s\\), the first in data row 51"
    with pytest.raises(CliError, match=message):
        run(str(path))


@pytest.mark.parametrize(
    ("text", "argv", "message"),
    [
        ("time,flow\n0,1\n1,2\n", [], "no pair of op_<loop> and pv_<loop> columns"),
        ("time,op_a,pv_a\n0,1,2\n1,1,2\n", ["--loops", "a,b"], "loop b: .*no column 'op_b'"),
        ("time,op_a,pv_a\n0,1,2\n1,1,2\n", ["--loops", "a,,b"], "empty loop name"),
        ("time,op_a,pv_a\n0,1,2\n1,1,2\n", ["--loops", "a,a"], "names a more than once"),
        ("time,op_a,pv_a\n0,1,2\n1,x,2\n", [], "row 3, column 'op_a': 'x' is not a number"),
        ("time,op_a,pv_a\n0,1,2\n1,1,2\n", [], "2 samples per signal, at least 64"),
    ],
)
def test_bad_input_says_what_and_where(tmp_path, text, argv, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(CliError, match=message):
        run(str(path), *argv)


def test_a_missing_file_is_a_user_error(tmp_path):
    with pytest.raises(CliError, match="no such file"):
        run(str(tmp_path / "absent.csv"))


def test_a_negative_skip_is_refused(tmp_path):
    with pytest.raises(CliError, match="--skip must be a number of seconds >= 0, got -1"):
        run(str(tmp_path / "any.csv"), "--skip", "-1")


def column_model_file(tmp_path, names=("loop1", "loop2", "loop3")) -> str:
    """The column's model in the format of ``loopwatch predict`` (its valves left out)."""
    model = column3x3()
    spec = {
        "dt": model.dt,
        "names": list(names),
        "process": {"matrix": [[g.to_dict() for g in row] for row in model.process]},
        "controllers": [loop.controller.to_dict() for loop in model.loops],
    }
    path = tmp_path / "column.json"
    path.write_text(json.dumps(spec))
    return str(path)


@pytest.mark.slow
def test_model_tests_every_sticky_set_against_the_cycle(column_csv, tmp_path, capsys):
    model = column_model_file(tmp_path)
    assert run(column_csv, "--loops", "loop1,loop2,loop3", "--skip", "2000", "--model", model,
               "--json") == 0
    report = json.loads(capsys.readouterr().out)
    assert report["k"] == 2
    assert {v["loop"] for v in report["sticky_valves"]} == {"loop1", "loop2"}
    assert report["model_used"] is True and report["linear"]["stable"] is True
    # Every non-empty set of the valves whose OP moves is tried.  A group's fingerprint may
    # add valve 3 beside a sticky one (3 of 8 seeds of this column); the replay decides.
    for group in report["groups"]:
        assert len(group["model"]["candidates"]) in (1, 3, 7)
        assert set(group["model"]["sticky_valves"]) & {"loop1", "loop2"}
    fast = min(report["groups"], key=lambda g: g["period_s"])["model"]
    assert len(fast["candidates"]) == 7 and fast["candidates"][0]["loops"] == ["loop1", "loop2"]
    assert run(column_csv, "--skip", "2000", "--model", model) == 0
    out = capsys.readouterr().out
    assert "model: the linear loops are stable" in out


@pytest.mark.slow
def test_without_a_model_the_report_asks_for_one(column_csv, capsys):
    assert run(column_csv, "--skip", "2000", "--json") == 0
    report = json.loads(capsys.readouterr().out)
    assert report["model_used"] is False and "would make it stronger" in report["note"]


def test_a_model_of_other_loops_is_refused(tmp_path):
    path = tmp_path / "unit.csv"
    k = np.arange(3000)
    rows = ["t,op_a,pv_a,op_b,pv_b"] + [f"{t},{np.sin(t / 9):.4f},{np.cos(t / 9):.4f},0,0"
                                        for t in k]
    path.write_text("\n".join(rows))
    model = column_model_file(tmp_path, names=("a", "b", "c"))
    with pytest.raises(CliError, match=r"the model's loops \['c'\] are not among the unit's"):
        run(str(path), "--model", model, "--loops", "a,b")
