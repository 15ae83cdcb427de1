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
    with pytest.raises(LoopCsvError, match=r"no time column .* name it .*--time.* or give the "
                                           r"sampling interval \(--ts\)"):
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
        ("t,op,pv\n0,1,2\n2,1,2\n2,1,2\n", r"rows 3 and 4: the same time"),
        ("t,flow,level\n0,1,2\n1,1,2\n", r"needs an 'op' or a 'pv' column"),
        ("t,op,pv\n0,1,2\n", r"1 data rows, at least 2 are needed"),
        ("t,op,pv\n0,1,2\n1,1\n", r"row 3: 2 cells, the header has 3"),
        ("t,op,pv\n0,1,2\nnoon,1,2\n", r"row 3, column 't': 'noon' is neither UNIX seconds nor"),
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


# ---------------------------------------------------------------- historian exports


def test_a_historian_export_newest_first_with_bom_date_time_and_null(tmp_path):
    path = tmp_path / "export.csv"
    path.write_bytes(
        "\ufeffid,date,time,FT_211,FV_211\n"
        "3,2024-11-27,00:02:00,NULL,37.5\n"
        "2,2024-11-27,00:01:00,102.5,37.25\n"
        "1,2024-11-27,00:00:00,102.0,37.0\n".encode())
    data = read_loop_csv(path, op="FV_211", pv="FT_211")
    np.testing.assert_array_equal(data.t, [0, 60, 120])
    np.testing.assert_array_equal(data.op, [37.0, 37.25, 37.5])
    np.testing.assert_array_equal(data.pv[:2], [102.0, 102.5])
    assert np.isnan(data.pv[2])
    assert data.ts == 60.0
    assert data.columns == {"op": "FV_211", "pv": "FT_211", "time": "date and time"}
    assert data.warnings == ()


def test_semicolons_with_decimal_commas(tmp_path):
    path = write(tmp_path, "Zeit;OP;PV\n0;12,5;-0,25\n1;13,0;1,5E1\n2;14;NULL\n")
    data = read_loop_csv(path, time="Zeit")
    np.testing.assert_array_equal(data.op, [12.5, 13.0, 14.0])
    np.testing.assert_array_equal(data.pv[:2], [-0.25, 15.0])


def test_a_ts_that_disagrees_with_the_time_column_is_warned_of_and_the_data_wins(tmp_path):
    path = write(tmp_path, "time,op\n0,1\n1,2\n2,3\n")
    data = read_loop_csv(path, ts=5)
    assert data.ts == 1.0
    assert data.warnings == (
        "--ts 5 s disagrees with the time column (time: median step 1 s); the time column is "
        "used (leave out --ts, or name another time column with --time)",)
    assert read_loop_csv(path, ts=1.0).warnings == ()


def test_a_semicolon_file_with_a_bad_cell_names_row_and_column(tmp_path):
    path = write(tmp_path, "t;op\n0;1,5\n1;1.234,5\n")
    with pytest.raises(LoopCsvError, match=r"row 3, column 'op': '1\.234,5' is not a number"):
        read_loop_csv(path)
