"""MATLAB files (.mat) as data: the variables are the columns, every problem a clear error.

Files are written with scipy's ``savemat`` (versions 4 and 5, as MATLAB's
``save`` writes them); no MATLAB here. The version 7.3 file is a MATLAB 7.3
header followed by HDF5's signature, written by hand: MATLAB and h5py are not
on this machine, and the reader refuses the file on its header alone.
"""

import json
import os
import subprocess
import sys
import threading

import numpy as np
import pytest
import scipy.io as sio

from spm_sysid.core.errors import DataError
from spm_sysid.core.io.data import load_data

from .conftest import ROOT


def cli(*args):
    return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)


@pytest.mark.parametrize("variables, fmt, inputs, output", [
    (lambda u, y: {"u": u, "y": y, "Ts": 0.01}, "5", None, None),  # row vectors, a number
    (lambda u, y: {"u": u[:, None], "y": y[:, None]}, "4", None, None),  # version 4
    (lambda u, y: {"data": {"torque": u[:, None], "acc": y[:, None]}}, "5", None, None),
    (lambda u, y: {"data": {"torque": u, "acc": y}}, "5", ["data.torque"], "data.acc"),
    (lambda u, y: {"M": np.column_stack([u, y])}, "5", None, None),  # one column each
    (lambda u, y: {"M": np.vstack([u, y])}, "5", ["M[0]"], "M[1]"),  # one row each
    (lambda u, y: {"uEst": u, "yEst": y, "uVal": u[:100], "yVal": y[:100]}, "5",
     ["uEst"], "yEst"),
    (lambda u, y: {"vir": u.astype(np.float32), "QM": y, "name": "take 3"}, "5",
     ["vir"], "qm"),  # single precision; a name in another case
])
def test_the_variables_are_the_columns(robot_arm, tmp_path, variables, fmt, inputs, output):
    u, y = robot_arm
    path = tmp_path / "take.mat"
    sio.savemat(path, variables(u, y), format=fmt)
    d = load_data(path, inputs, output)
    expect_u = u.astype(np.float32).astype(float) if inputs == ["vir"] else u
    np.testing.assert_array_equal(d.u, expect_u)
    np.testing.assert_array_equal(d.y, y)
    assert d.t is None and d.rejected == 0


def test_identify_on_a_mat_file_gives_the_text_files_model(robot_arm, robot_arm_path,
                                                          tmp_path):
    """The command as a user types it, on the robot arm saved from MATLAB and as text."""
    u, y = robot_arm
    mat = tmp_path / "arm.mat"
    sio.savemat(mat, {"torque": u[:, None], "acc": y[:, None], "Ts": 0.01})
    models = []
    for data, name in ((mat, "a.json"), (robot_arm_path, "b.json")):
        r = cli("identify", "--data", str(data), "--json", str(tmp_path / name))
        assert r.returncode == 0, r.stderr
        models.append(json.loads((tmp_path / name).read_text()))
    assert models[0]["terms"] == models[1]["terms"]  # unnamed signals: u and y, both
    np.testing.assert_allclose(models[0]["coefficients"], models[1]["coefficients"],
                               rtol=1e-12)
    values = [m["criterion"]["value"] for m in models]
    assert values[0] == pytest.approx(values[1], rel=1e-12)
    assert values[0] == pytest.approx(-10744.78, abs=0.01)  # the paper's AIC optimum


def test_a_time_variable_drops_missing_samples_and_counts_them(robot_arm, tmp_path):
    u, y = robot_arm
    y = y.copy()
    y[100:105] = np.nan
    path = tmp_path / "timed.mat"
    sio.savemat(path, {"t": np.arange(1024) * 0.01, "torque": u, "acc": y})
    d = load_data(path)
    assert d.rejected == 5 and len(d.y) == 1019 and d.t[100] == pytest.approx(1.05)
    r = cli("identify", "--data", str(path), "--generations", "10", "--quiet")
    assert r.returncode == 0, r.stderr
    assert "5 rejected as NaN/inf" in r.stdout + r.stderr


def test_a_pipe_holding_a_mat_file_is_read_by_its_header(robot_arm, tmp_path):
    u, y = robot_arm
    src = tmp_path / "arm.mat"
    sio.savemat(src, {"u": u, "y": y})
    fifo = tmp_path / "stream"
    os.mkfifo(fifo)

    def feed():
        with open(fifo, "wb") as f:
            f.write(src.read_bytes())

    writer = threading.Thread(target=feed)
    writer.start()
    d = load_data(fifo)
    writer.join()
    np.testing.assert_array_equal(d.y, y)


def test_text_saved_under_a_mat_name_is_read_as_text(robot_arm, tmp_path):
    """MATLAB's ``save take.mat u y -ascii`` writes text: read as the two columns it holds."""
    u, y = robot_arm
    path = tmp_path / "take.mat"
    np.savetxt(path, np.column_stack([u, y]), fmt="%.8e")
    d = load_data(path)
    np.testing.assert_allclose(d.u, u, rtol=1e-8)
    np.testing.assert_allclose(d.y, y, rtol=1e-8)


def _v73(path, like):
    """A MATLAB 7.3 header (version 0x0200) and HDF5's signature at byte 512."""
    head = bytearray(like.read_bytes()[:128])
    head[:19] = b"MATLAB 7.3 MAT-file"
    head[124:126] = b"\x00\x02"
    path.write_bytes(bytes(head) + b"\0" * 384 + b"\x89HDF\r\n\x1a\n" + b"\0" * 64)


@pytest.mark.parametrize("case, inputs, output, message", [
    ("several", None, None, "name the input and the output (--inputs and --output"),
    ("several", ["uEst"], "yVal", "the signals differ in length (uEst 600, yVal 424"),
    ("several", ["uest"], "yX", "no signal 'yX' (it holds uEst (600 samples), yEst (600 "
                                "samples), uVal (424 samples), yVal (424 samples); not "
                                "signals (numbers, text, cells, complex or deeper structs): fs"),
    ("lengths", None, None, "the signals differ in length (u 1024, y 1000 samples)"),
    ("nan", None, None, "row 101: value 'nan' is not finite"),
    ("nothing", None, None, "no signal (a numeric vector of two or more samples) in the "
                            "file; it holds no signal; not signals (numbers, text, cells, "
                            "complex or deeper structs): Ts, name, z"),
    ("garbage", None, None, "is not a readable MATLAB file (ValueError"),
    ("cut", None, None, "is not a readable MATLAB file"),
    ("v73", None, None, "is a MATLAB version 7.3 (HDF5) file, which is not read here: save "
                        "it with save(file, ..., '-v7') or export a CSV"),
])
def test_bad_mat_files_give_one_clear_error(robot_arm, tmp_path, case, inputs, output,
                                            message):
    u, y = robot_arm
    path = tmp_path / "take.mat"
    good = tmp_path / "good.mat"
    sio.savemat(good, {"u": u, "y": y})
    bad = y.copy()
    bad[100] = np.nan
    if case == "several":
        sio.savemat(path, {"uEst": u[:600], "yEst": y[:600], "uVal": u[600:], "yVal": y[600:],
                           "fs": 100.0})
    elif case == "lengths":
        sio.savemat(path, {"u": u, "y": y[:1000]})
    elif case == "nan":
        sio.savemat(path, {"u": u, "y": bad})
    elif case == "nothing":
        sio.savemat(path, {"Ts": 0.01, "name": "take", "z": u + 1j * y})
    elif case == "garbage":
        path.write_bytes(bytes(range(256)) * 4)  # binary, not MATLAB
    elif case == "cut":
        path.write_bytes(good.read_bytes()[:4000])
    else:
        _v73(path, good)
    with pytest.raises(DataError) as err:
        load_data(path, inputs, output)
    assert message in str(err.value)
    r = cli("identify", "--data", str(path), *(["--inputs", *inputs] if inputs else []),
            *(["--output", output] if output else []), "--quiet")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and message in r.stderr, r.stderr
