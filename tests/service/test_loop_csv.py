"""Reading loop data from CSV: names, time formats and precise errors."""

import numpy as np
import pytest

from service.loop_csv import LoopCsvError, read_loop_csv


def write(tmp_path, text, name="loop.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_columns_are_found_case_insensitively(tmp_path):
    path = write(tmp_path, "T_S,OP,Pv,SP\n0,50,1.0,1\n2,51,1.5,1\n4,52,2.0,1\n")
    data = read_loop_csv(path)
    assert data.ts == 2.0
    np.testing.assert_array_equal(data.t, [0, 2, 4])
    np.testing.assert_array_equal(data.op, [50, 51, 52])
    np.testing.assert_array_equal(data.pv, [1.0, 1.5, 2.0])
    assert data.mv is None
    assert data.columns == {"op": "OP", "pv": "Pv", "sp": "SP", "time": "T_S"}


def test_iso_timestamps_and_explicit_column_names(tmp_path):
    path = write(
        tmp_path,
        "when,FV_211,FT_211\n2024-11-21T00:00:00Z,10,5\n2024-11-21T00:01:00Z,11,6\n"
        "2024-11-21T00:02:00Z,12,7\n",
    )
    data = read_loop_csv(path, time="when", op="fv_211", pv="FT_211")
    np.testing.assert_array_equal(data.t, [0, 60, 120])
    assert data.ts == 60.0


def test_without_time_column_ts_is_required(tmp_path):
    path = write(tmp_path, "op,pv\n1,2\n3,4\n")
    with pytest.raises(LoopCsvError, match=r"no time column .* give --time or --ts"):
        read_loop_csv(path)
    data = read_loop_csv(path, ts=0.5)
    np.testing.assert_array_equal(data.t, [0, 0.5])


def test_missing_cells_become_nan_for_the_quality_screen(tmp_path):
    data = read_loop_csv(write(tmp_path, "t,op,pv\n0,1,\n1,nan,2\n2,3,4\n"))
    assert np.isnan(data.pv[0]) and np.isnan(data.op[1])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("t,op,pv\n0,1,2\n1,abc,3\n", r"row 3, column 'op': 'abc' is not a number"),
        ("t,op,pv\n0,1,2\n2,1,2\n1,1,2\n", r"row 4: time 1 does not increase \(previous row 3"),
        ("t,op,pv\n0,1,2\n0,1,2\n", r"row 3: time 0 does not increase"),
        ("t,flow,level\n0,1,2\n1,1,2\n", r"needs an 'op' or a 'pv' column"),
        ("t,op,pv\n0,1,2\n", r"1 data rows, at least 2 are needed"),
        ("t,op,pv\n0,1,2\n1,1\n", r"row 3: 2 cells, the header has 3"),
        ("t,op,pv\n0,1,2\nnoon,1,2\n", r"row 3, column 't': 'noon' is neither seconds nor"),
        ("", r"the file is empty"),
    ],
)
def test_bad_files_are_refused_with_file_row_and_column(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(LoopCsvError, match=message) as info:
        read_loop_csv(path)
    assert str(path) in str(info.value)


def test_unknown_explicit_column_and_missing_file(tmp_path):
    path = write(tmp_path, "t,op,pv\n0,1,2\n1,1,2\n")
    with pytest.raises(LoopCsvError, match=r"no column 'valve'; the header has t, op, pv"):
        read_loop_csv(path, op="valve")
    with pytest.raises(LoopCsvError, match="no such file"):
        read_loop_csv(tmp_path / "absent.csv")
    with pytest.raises(LoopCsvError, match="--ts must be a positive"):
        read_loop_csv(path, ts=0.0)
