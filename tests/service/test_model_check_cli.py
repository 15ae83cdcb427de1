"""``loopwatch model-check`` (service.commands.model_check), on a parser built here.

The data are loops with a known hidden effect (analytics.model_check.cases)
written as CSV files like the ones ``loopwatch analyze`` reads.
"""

import argparse
import csv
import json
from pathlib import Path

import numpy as np
import pytest

from analytics.model_check.cases import HiddenEffectCase, hidden_effect_case
from analytics.scenarios import chapter4
from service.commands import CliError
from service.commands.model_check import register


def run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="loopwatch")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["model-check", *argv])
    return int(args.handler(args))


def write_csv(path: Path, columns: dict[str, np.ndarray]) -> Path:
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        writer.writerows(zip(*(np.round(v, 9) for v in columns.values()), strict=True))
    return path


def case_files(tmp_path: Path, case: HiddenEffectCase) -> tuple[Path, Path]:
    t = np.arange(case.op.size) * case.ts
    data = write_csv(
        tmp_path / "loop.csv", {"time": t, "sp": case.sp, "op": case.op, "pv": case.pv}
    )
    model = tmp_path / "model.json"
    model.write_text(json.dumps(case.base_model.to_dict()))
    return data, model


@pytest.fixture(scope="module")
def gain_case() -> HiddenEffectCase:
    return hidden_effect_case("gain_mismatch", 3, samples=3000)


def test_json_report_names_the_hidden_effect(tmp_path, capsys, gain_case) -> None:
    data, model = case_files(tmp_path, gain_case)
    assert run([str(data), "--model", str(model), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["model_source"] == "given"
    assert out["cause"]["effect"] == "gain_mismatch"
    assert out["cause"]["parameters"]["K"] == pytest.approx(
        gain_case.true_model.process.K, rel=0.03
    )
    assert out["gain"]["nmse_after"] < out["gain"]["nmse_before"] == out["baseline"]["nmse"]
    assert out["extended_model"]["process"]["K"] == out["cause"]["parameters"]["K"]
    assert len(out["candidates"]) == 8 and "overlay" not in out
    # issue 21: the runner-up and the list of causes, each with its gain
    assert out["cause"]["runner_up"] in {c["effect"] for c in out["candidates"]} - {"gain_mismatch"}
    assert out["causes"][0] == out["cause"]
    assert out["cause"]["nmse_before"] == out["gain"]["nmse_before"]
    assert out["causes"][-1]["nmse_after"] == out["gain"]["nmse_after"]


def test_readable_report(tmp_path, capsys, gain_case) -> None:
    data, model = case_files(tmp_path, gain_case)
    assert run([str(data), "--model", str(model)]) == 0
    out = capsys.readouterr().out
    assert "cause: gain_mismatch" in out and "runner-up" in out
    assert "findings:" in out and "The process gain is" in out
    assert '"process"' in out  # the extended model, as JSON


def test_overlay_for_plotting(tmp_path, capsys, gain_case) -> None:
    data, model = case_files(tmp_path, gain_case)
    assert run([str(data), "--model", str(model), "--json", "--overlay"]) == 0
    overlay = json.loads(capsys.readouterr().out)["overlay"]
    assert len(overlay["t"]) == len(overlay["pv_extended"]) == 3000
    assert sum(overlay["scored"]) > 2000


def test_without_a_model_the_loop_is_identified(tmp_path, capsys) -> None:
    res = chapter4().run()
    data = write_csv(
        tmp_path / "ch4.csv", {"t_s": res.t, "op": res.op[0], "pv": res.pv[0], "sp": res.sp[0]}
    )
    assert run([str(data), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["model_source"] == "identified"
    assert out["baseline"]["nmse"] < 0.1
    assert any("Hammerstein" in note for note in out["notes"])


def test_a_simulation_written_to_six_digits_is_not_blamed_on_quantisation(
        tmp_path, capsys) -> None:
    """QA: ``loopwatch simulate chapter4`` writes 6 significant digits, so its noise-free
    PV, settled while the valve sticks, lies on a grid of 1e-4 and repeats.  That rounding
    (variance 8e-10) can remove nothing of the identified model's held-out NMSE of 0.03,
    yet the check named measurement quantisation the cause."""
    from service.commands.simulate import write_csv as write_simulation

    data = tmp_path / "ch4.csv"
    with data.open("w", newline="") as handle:
        write_simulation(chapter4().run(), handle)
    pv = np.loadtxt(data, delimiter=",", skiprows=1, usecols=4)
    assert np.mean(np.diff(pv[1000:]) == 0) > 0.25  # the PV repeats: it is on a lattice
    assert run([str(data), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["baseline"]["nmse"] > 0.01
    assert (out["cause"] or {}).get("effect") != "measurement_quantization", out["findings"]
    assert not any("grid" in finding for finding in out["findings"])


@pytest.mark.parametrize(
    ("model_text", "message"),
    [
        (None, "no such file"),
        ('{"dt": 1,', "invalid JSON at line 1, column 10"),
        ('{"dt": 1, "process": {"type": "fopdt", "K": 1, "tau": 5}}',
         "lacks the key(s) 'controller'"),
        ('{"dt": 1, "process": {"type": "fopdt", "K": 1, "tau": 5}, "controller": {"Kc": 1},'
         ' "valve": {"model": "he", "fs": 1, "fd": 3}}', "fd=3.0 cannot exceed static"),
    ],
)
def test_bad_model_files_say_what_is_wrong(tmp_path, gain_case, model_text, message) -> None:
    data, model = case_files(tmp_path, gain_case)
    if model_text is None:
        model.unlink()
    else:
        model.write_text(model_text)
    with pytest.raises(CliError, match=message.replace("(", r"\(").replace(")", r"\)")) as err:
        run([str(data), "--model", str(model)])
    assert str(model) in str(err.value)


def test_missing_values_are_refused_with_their_place(tmp_path, gain_case) -> None:
    t = np.arange(gain_case.op.size) * gain_case.ts
    pv = gain_case.pv.copy()
    pv[[40, 41]] = np.nan
    data = write_csv(tmp_path / "gaps.csv", {"time": t, "op": gain_case.op, "pv": pv})
    with pytest.raises(CliError, match=r"PV holds 2 missing or non-finite value.*sample 40"):
        run([str(data)])


def test_a_file_without_pv_is_refused(tmp_path, gain_case) -> None:
    t = np.arange(gain_case.op.size) * gain_case.ts
    data = write_csv(tmp_path / "op_only.csv", {"time": t, "op": gain_case.op})
    with pytest.raises(CliError, match="needs both OP and PV; no 'pv' column"):
        run([str(data)])


def test_irregular_sampling_is_refused(tmp_path, gain_case) -> None:
    t = np.arange(gain_case.op.size) * gain_case.ts
    t[500:] += 30.0  # a 30 s gap
    data = write_csv(tmp_path / "gap.csv", {"time": t, "op": gain_case.op, "pv": gain_case.pv})
    with pytest.raises(CliError, match=r"irregular .* first between samples 499 and 500"):
        run([str(data)])


def test_too_short_a_file_is_refused(tmp_path, gain_case) -> None:
    n = 100
    data = write_csv(
        tmp_path / "short.csv",
        {"time": np.arange(n) * 1.0, "op": gain_case.op[:n], "pv": gain_case.pv[:n]},
    )
    with pytest.raises(CliError, match="at least 300 are needed"):
        run([str(data)])
