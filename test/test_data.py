"""Data loading: formats, every malformed-input error, and the robot-arm loader."""

import gzip
import http.server
import re
import threading

import numpy as np
import pytest

from spm_sysid.core.errors import DataError
from spm_sysid.core.identify import check_samples, identify
from spm_sysid.core.io import datasets as data_mod
from spm_sysid.core.io.data import load_data, load_io, parse_table
from spm_sysid.core.io.datasets import (
    ROBOT_ARM_SHA256,
    download_robot_arm,
    find_robot_arm,
    numeric_sha256,
)


def test_robot_arm_file_is_the_known_data(robot_arm):
    u, y = robot_arm
    assert len(u) == len(y) == 1024
    assert numeric_sha256(np.column_stack([u, y])) == ROBOT_ARM_SHA256
    assert y.min() == pytest.approx(-0.78827423) and y.max() == pytest.approx(0.78911527)


def test_csv_with_header_and_column_names(tmp_path):
    p = tmp_path / "d.csv"
    p.write_text("time,y,u\n0,1.5,0.1\n1,2.5,0.2\n")
    u, y = load_io(p)
    assert u.tolist() == [0.1, 0.2] and y.tolist() == [1.5, 2.5]
    p.write_text("torque,accel\n0.1,1.5\n0.2,2.5\n")
    u, y = load_io(p)
    assert u.tolist() == [0.1, 0.2] and y.tolist() == [1.5, 2.5]


def test_two_column_text_with_comments_and_gzip(tmp_path):
    p = tmp_path / "d.dat"
    p.write_text("# comment\n1.0 2.0\n\n3.0\t4.0\r\n")
    assert [a.tolist() for a in load_io(p)] == [[1.0, 3.0], [2.0, 4.0]]
    g = tmp_path / "d.dat.gz"
    g.write_bytes(gzip.compress(p.read_bytes()))
    assert [a.tolist() for a in load_io(g)] == [[1.0, 3.0], [2.0, 4.0]]


@pytest.mark.parametrize("content, names, values", [
    ("time;u;y\n0;-0,138;1,5\n0,01;2,25;-,5e-1\n", ["time", "u", "y"],
     [[0.0, -0.138, 1.5], [0.01, 2.25, -0.05]]),
    ("0,5;1,25\n0,75;1,5\n", None, [[0.5, 1.25], [0.75, 1.5]]),
    ("u\ty\n0,5\t1,25\n", ["u", "y"], [[0.5, 1.25]]),
    ("0,5 1,25\n-1,0 2\n", None, [[0.5, 1.25], [-1.0, 2.0]]),
    ("u,y\n1,2\n3,4\n", ["u", "y"], [[1.0, 2.0], [3.0, 4.0]]),  # commas separate
    ("1.0, 2.0\n3, 4\n", None, [[1.0, 2.0], [3.0, 4.0]]),
    ("u;y\n1.5;2\n", ["u", "y"], [[1.5, 2.0]]),
    ("u;y\n0;1\n0,5;1,25\n", ["u", "y"], [[0.0, 1.0], [0.5, 1.25]]),  # whole first row
    ("0;1\n0,5;1,25\n", None, [[0.0, 1.0], [0.5, 1.25]]),  # and no header
    ('"torque, Nm","acc"\n1,2\n', ["torque, nm", "acc"], [[1.0, 2.0]]),  # quoted separator
])
def test_separators_and_decimal_commas(content, names, values):
    """Spreadsheets in many locales export ``0,25;1,5``: semicolons separate, commas mark."""
    table = parse_table(content, "take.csv")
    assert table.names == names and table.values.tolist() == values


def test_a_units_line_after_the_header_is_named(tmp_path):
    p = tmp_path / "take.tsv"
    p.write_text("time\tu\ty\ns\tNm\trad\n0\t1\t2\n")
    with pytest.raises(DataError, match=r"line 2: 's' is not a number; line 2 holds no number "
                                        r"at all: a second header line \(units\?\)"):
        load_io(p)
    p.write_text("time\tu\ty\n# s\tNm\trad\n0\t1\t2\n0.01\t3\t4\n")
    u, y = load_io(p)  # the units as a comment: read
    assert u.tolist() == [1.0, 3.0] and y.tolist() == [2.0, 4.0]


@pytest.mark.parametrize("first, step, unit", [
    (1.7e18, 1e6, "nanoseconds"),      # ROS stamps: ns since 1970, 1 kHz
    (0.0, 1e7, "nanoseconds"),         # ns from the record's start, 100 Hz
    (1.7e15, 1e3, "microseconds"),
    (1.7e12, 10.0, "milliseconds"),
    (1.7e9, 0.01, ""),                 # seconds since 1970
    (0.0, 60.0, ""),                   # a sample a minute, in seconds
])
def test_the_time_columns_unit_is_told_from_its_values_and_said(tmp_path, first, step, unit):
    """A ROS export stamps rows in nanoseconds: read as seconds, 1.7e18 overflowed."""
    from spm_sysid.core.record import DataSpec, load_record

    scale = {"nanoseconds": 1e-9, "microseconds": 1e-6, "milliseconds": 1e-3, "": 1.0}[unit]
    times = first + step * np.r_[np.arange(40), np.arange(60, 100)]  # a gap of 20 samples
    rng = np.random.default_rng(0)
    p = tmp_path / "take.csv"
    p.write_text("timestamp,u,y\n" + "".join(f"{t:.0f},{a:.6f},{b:.6f}\n" if step >= 1
                                              else f"{t:.3f},{a:.6f},{b:.6f}\n"
                                              for t, a, b in zip(times, *rng.random((2, 80)))))
    record = load_record(DataSpec(data=(str(p),)))
    # rtol: a float64 holds ns since 1970 to 256 ns
    assert np.allclose(np.diff(record.stamps_ns) * 1e-9, np.diff(times) * scale, rtol=1e-3)
    assert record.segment_info().gaps == 1
    said = [n for n in record.notes if "time column" in n]
    assert (unit in said[0] and "'timestamp'" in said[0]) if unit else not said


def test_cells_that_say_a_value_is_missing_are_gaps_and_counted(tmp_path):
    """R writes NA, spreadsheets #N/A, databases null: rows dropped as gaps, each counted."""
    from spm_sysid.core.record import DataSpec, load_record

    rng = np.random.default_rng(1)
    rows = [f"{0.01 * t:.2f},{a:.6f},{b:.6f}" for t, (a, b) in enumerate(rng.random((200, 2)))]
    missing = {20: "NA", 50: "N/A", 80: "#N/A", 110: "null", 140: "", 170: "nan"}
    for i, token in missing.items():
        rows[i] = rows[i].rsplit(",", 1)[0] + "," + token
    p = tmp_path / "take.csv"
    p.write_text("time,u,y\n" + "\n".join(rows) + "\n")
    record = load_record(DataSpec(data=(str(p),)))
    assert record.rejected == len(missing) and len(record.y) == 200 - len(missing)
    assert record.segment_info().gaps == len(missing)
    kept = [i for i in range(200) if i not in missing]
    assert np.allclose(record.y, [float(rows[i].rsplit(",", 1)[1]) for i in kept])


@pytest.mark.parametrize("header, scale", [("time [ms]", 1e-3), ("t (s)", 1.0),
                                           ("timestamp_ns", 1e-9), ("Time [us]", 1e-6),
                                           ("time [min]", 60.0)])
def test_a_time_unit_in_the_header_is_used(tmp_path, header, scale):
    """``time [ms]`` counting from 0: as seconds it would put a second between samples."""
    from spm_sysid.core.record import DataSpec, load_record

    p = tmp_path / "take.csv"
    times = np.r_[np.arange(30), np.arange(40, 70)]
    p.write_text(f"{header},u,y\n" + "".join(f"{t},{t % 3},{t % 5}\n" for t in times))
    record = load_record(DataSpec(data=(str(p),)))
    assert np.allclose(np.diff(record.stamps_ns), np.diff(times) * scale * 1e9)
    assert record.segment_info().gaps == 1 and not record.notes


def test_iso_date_times_in_the_time_column(tmp_path):
    """pandas' ``to_csv`` and loggers write ``2024-05-01 12:00:00.010``: read as seconds."""
    from spm_sysid.core.record import DataSpec, load_record

    p = tmp_path / "take.csv"
    ms = np.r_[np.arange(40), np.arange(60, 100)] * 10  # 100 Hz, a gap of 20 samples
    p.write_text("time,u,y\n" + "".join(
        f"2024-05-01{'T' if k % 2 else ' '}12:00:{t // 1000:02d}.{t % 1000:03d}"
        f"{'Z' if k % 3 == 0 else ''},{k % 3},{k % 5}\n" for k, t in enumerate(ms)))
    record = load_record(DataSpec(data=(str(p),)))
    assert np.allclose(np.diff(record.stamps_ns), np.diff(ms) * 1e6, atol=1e3)
    assert record.segment_info().gaps == 1 and len(record.y) == 80
    p.write_text("time,u,y\n2024-05-01 12:00:00,1,2\n01-May-2024 12:00:01,1,2\n")
    with pytest.raises(DataError, match="line 3: the time column holds '01-May-2024 12:00:01', "
                                        "neither a number nor an ISO 8601 date-time"):
        load_io(p)


def test_units_in_headers_are_not_part_of_the_signals_names(tmp_path):
    """``Torque [Nm]`` was not an identifier: the model said u and y, and validate could not
    find the columns again."""
    p = tmp_path / "take.csv"
    p.write_text("time [s],Torque [Nm],position (rad),q [deg]\n0,1,2,3\n0.01,4,5,6\n")
    d = load_data(p, ["Torque [Nm]"], "position (rad)")
    assert d.input_names == ("torque",) and d.output_name == "position"
    d = load_data(p, ["torque"], "position")  # found again by the names the model has
    assert d.u.tolist() == [1.0, 4.0] and d.y.tolist() == [2.0, 5.0]
    p.write_text("t,q [rad],q [deg],u\n0,1,2,3\n0.01,4,5,6\n")
    with pytest.raises(DataError, match=r"'q' names the columns \['q \[rad\]', 'q \[deg\]'\]"):
        load_data(p, ["u"], "q")
    d = load_data(p, ["q [deg]"], "q [rad]")  # one name for both: the defaults
    assert d.input_names == ("u",) and d.output_name == "y"


@pytest.mark.parametrize("index", ["", "Unnamed: 0"])
def test_pandas_row_numbers_are_left_out_of_the_default_layout(tmp_path, index):
    """``df.to_csv()`` writes its index first, unnamed: 'exactly 2 columns, found 3'."""
    from spm_sysid.core.record import DataSpec, load_record

    p = tmp_path / "take.csv"
    p.write_text(f"{index},time,torque,acc\n0,0.0,1,2\n1,0.01,3,4\n2,0.02,5,6\n")
    record = load_record(DataSpec(data=(str(p),)))
    assert record.u.tolist() == [1.0, 3.0, 5.0] and record.y.tolist() == [2.0, 4.0, 6.0]
    assert record.notes == [f"{p}: column 0 ({index!r}: a row number, pandas' "
                            "index?) left out"]
    p.write_text("torque;acc;\n1;2;\n3;4;\n")  # a separator at every line's end
    record = load_record(DataSpec(data=(str(p),)))
    assert record.u.tolist() == [1.0, 3.0] and record.y.tolist() == [2.0, 4.0]
    assert record.notes == [f"{p}: column 2 ('': empty: a separator at the end of each "
                            "line?) left out"]
    p.write_text("u,y,\n1,2,\n3,4,\n")  # named u and y: nothing to say
    assert load_record(DataSpec(data=(str(p),))).notes == []


def test_a_loggers_repeated_rows_are_dropped_and_said(tmp_path):
    """The same time and values twice: 'the time column must increase' stopped the read."""
    from spm_sysid.core.record import DataSpec, load_record

    p = tmp_path / "take.csv"
    p.write_text("time,u,y\n0,1,2\n0.01,3,4\n0.01,3,4\n0.02,5,6\n0.02,5,6\n0.03,7,8\n")
    record = load_record(DataSpec(data=(str(p),)))
    assert record.u.tolist() == [1.0, 3.0, 5.0, 7.0] and record.segment_info().gaps == 0
    assert record.notes == [f"{p}: 2 row(s) repeating the row before (the same time and "
                            "values: a logger's duplicates?) dropped"]
    p.write_text("time,u,y\n0,1,2\n0.01,3,4\n0.01,3,5\n")  # one time, two values: which?
    with pytest.raises(DataError, match="line 4: the time column must increase"):
        load_record(DataSpec(data=(str(p),)))


def test_plotjugglers_time_column(tmp_path):
    p = tmp_path / "pj.csv"
    p.write_text("__time,/joint/effort,/joint/position\n1700000000.000,1,2\n"
                 "1700000000.001,3,4\n1700000000.005,5,6\n")
    d = load_data(p, ["/joint/effort"], "/joint/position")
    assert np.allclose(np.diff(d.t), [0.001, 0.004], rtol=1e-3) and d.y.tolist() == [2.0, 4.0, 6.0]


@pytest.mark.parametrize("content, message", [
    ("1.0 2.0\n3.0\n", "line 2: expected 2 columns"),
    ("1.0 2.0 3.0\n", "line 1: expected 2 columns"),
    ("1.0 2.0\n1.0 abc\n", "line 2: 'abc' is not a number"),
    ("1.0 2.0\nnan 1.0\n", "line 2: value 'nan' is not finite"),
    ("1.0 inf\n", "line 1: value 'inf' is not finite"),
    ("", "empty"),
    ("a,b,c\n1,2,3\n", "needs columns named 'u' and 'y'"),
    ("u,y\n", "no data rows"),
    ("u,y\n1,2\n3\n", "line 3: expected 2 columns"),
    ("u,y\n1,x\n", "'x' is not a number"),
    ("u,y\n1,2\n3,NA\n", "line 3: a value is missing \\('NA'; add a time column"),
    ("u,y\n1,2\n#N/A,4\n", "line 3: a value is missing \\('#N/A'"),
])
def test_malformed_files_give_clear_errors(tmp_path, content, message):
    p = tmp_path / "bad.txt"
    p.write_text(content)
    with pytest.raises(DataError, match=message):
        load_io(p)


def test_missing_directory_and_binary_files(tmp_path):
    with pytest.raises(DataError, match="not found"):
        load_io(tmp_path / "nope.dat")
    with pytest.raises(DataError, match="directory"):
        load_io(tmp_path)
    b = tmp_path / "bin.dat"
    b.write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(DataError, match="not a text file"):
        load_io(b)


@pytest.mark.parametrize("head, what", [
    (b"PK\x03\x04\x14\x00\x00\x00", "a ZIP archive, as an Excel workbook (.xlsx) is: save "
                                       "the sheet as CSV"),
    (b"\xd0\xcf\x11\xe0\xa1\xb1\x1a\xe1\x00", "an Excel 97-2003 workbook"),
    (b"PAR1\x15\x04\x00", "a Parquet file: write it as CSV"),
    (b"\x89HDF\r\n\x1a\n\x00", "an HDF5 file"),
])
def test_binary_tables_are_named_with_what_to_do(tmp_path, head, what):
    b = tmp_path / "take.bin"
    b.write_bytes(head + bytes(64))
    with pytest.raises(DataError, match=f"take.bin is {re.escape(what)}"):
        load_io(b)


def test_windows_1252_text_is_read_and_said(tmp_path):
    """Western spreadsheets save "°C" and "µ" in Windows-1252: 'not a text file' before."""
    from spm_sysid.core.record import DataSpec, load_record

    p = tmp_path / "take.csv"
    p.write_bytes("time;Drehmoment [µNm];Temperatur [°C]\n0;1;20,5\n0,01;2;20,7\n"
                  .encode("cp1252"))
    record = load_record(DataSpec(data=(str(p),), inputs=("Drehmoment [µNm]",),
                                  output="Temperatur [°C]"))
    assert record.u.tolist() == [1.0, 2.0] and record.y.tolist() == [20.5, 20.7]
    assert record.input_names == ("drehmoment",) and record.output_name == "temperatur"
    assert record.notes == [f"{p}: not UTF-8; read as Windows-1252 (a spreadsheet's export)"]


def test_too_few_samples_and_bad_signals():
    with pytest.raises(DataError, match="too few samples"):
        check_samples(40, 4, 44)
    with pytest.raises(DataError, match="too few samples"):
        identify(u=np.zeros(30), y=np.ones(30))
    with pytest.raises(DataError, match="same length"):
        identify(u=np.zeros(100), y=np.ones(99))
    y = np.ones(100)
    y[17] = np.nan
    with pytest.raises(DataError, match="non-finite.*index 17"):
        identify(u=np.zeros(100), y=y)


def test_find_robot_arm_search_order(tmp_path, monkeypatch, robot_arm_path):
    explicit = tmp_path / "mine.dat"
    explicit.write_text("1 2\n")
    assert find_robot_arm(explicit) == explicit
    with pytest.raises(DataError, match="explicit path"):
        find_robot_arm(tmp_path / "missing.dat")
    monkeypatch.setenv("SPM_SYSID_ROBOT_ARM", str(explicit))
    assert find_robot_arm() == explicit
    monkeypatch.setenv("SPM_SYSID_ROBOT_ARM", str(tmp_path / "gone.dat"))
    with pytest.raises(DataError, match="SPM_SYSID_ROBOT_ARM"):
        find_robot_arm()
    monkeypatch.delenv("SPM_SYSID_ROBOT_ARM")
    assert find_robot_arm() == robot_arm_path  # ../shared/data from the project root
    # nothing anywhere: the message says where it looked and how to fetch it
    monkeypatch.setattr(data_mod, "_candidates", lambda p: [("user cache", tmp_path / "x.dat")])
    with pytest.raises(DataError, match="fetch-data"):
        find_robot_arm()


@pytest.fixture
def http_server(tmp_path):
    """A real HTTP server on 127.0.0.1 serving files from tmp_path/www."""
    root = tmp_path / "www"
    root.mkdir()

    class Handler(http.server.SimpleHTTPRequestHandler):
        def __init__(self, *a, **kw):
            super().__init__(*a, directory=str(root), **kw)

        def log_message(self, *a):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield root, f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


def test_download_from_local_server_with_checksum(http_server, tmp_path, robot_arm_path):
    root, base = http_server
    # the DaISy layout: tab-separated, trailing tab, CRLF, gzip-compressed
    lines = robot_arm_path.read_text().splitlines()
    daisy = "".join("   " + "\t  ".join(ln.split()) + "\t\r\n" for ln in lines)
    (root / "robot_arm.dat.gz").write_bytes(gzip.compress(daisy.encode()))
    dest = tmp_path / "cache" / "robot_arm.dat"
    path = download_robot_arm(url=f"{base}/robot_arm.dat.gz", dest=dest)
    assert path == dest
    u, y = load_io(path)
    assert numeric_sha256(np.column_stack([u, y])) == ROBOT_ARM_SHA256

    # one changed digit: rejected, nothing written
    tampered = daisy.replace("2.2183165e-01", "2.2183166e-01", 1)
    (root / "bad.dat.gz").write_bytes(gzip.compress(tampered.encode()))
    other = tmp_path / "cache2" / "robot_arm.dat"
    with pytest.raises(DataError, match="checksum mismatch"):
        download_robot_arm(url=f"{base}/bad.dat.gz", dest=other)
    assert not other.exists()
    with pytest.raises(DataError, match="could not download"):
        download_robot_arm(url=f"{base}/missing.gz", dest=other)
