"""Files (core/files.py): data read once, files that are only ever files, inputs never overwritten.

Each test reproduces a case that lost or destroyed something before the fix.
"""

import gzip
import json
import os
import re
import shutil
import stat
import subprocess
import sys
import threading

import numpy as np
import pytest

from spm_sysid.core.errors import DataError, FileCheckError, ModelFormatError
from spm_sysid.core.files import atomic_write_text
from spm_sysid.core.io.data import load_data
from spm_sysid.core.model.narx import NarxModel
from spm_sysid.core.model.terms import TermSpace

from .conftest import ROOT

QUICK = ["--generations", "20", "--population-size", "40", "--seed", "1", "--quiet",
         "--validation", "none"]


def cli(*args, env=None, timeout=300, **kw):
    return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                          capture_output=True, text=True, cwd=ROOT, timeout=timeout, env=env,
                          **kw)


# -- reading: one handle, regular files and pipes only ------------------------------------


def test_a_named_pipe_is_read_whole(robot_arm_path, tmp_path):
    fifo = tmp_path / "stream"
    os.mkfifo(fifo)
    data = robot_arm_path.read_bytes()

    def feed():
        with open(fifo, "wb") as f:
            f.write(data)

    threading.Thread(target=feed, daemon=True).start()
    piped = load_data(fifo)
    direct = load_data(robot_arm_path)
    assert len(piped.u) == len(direct.u) == 1024
    np.testing.assert_array_equal(piped.u, direct.u)
    np.testing.assert_array_equal(piped.y, direct.y)


def test_identify_from_stdin_and_process_substitution(robot_arm_path, tmp_path):
    """The review's case: 848 of 1024 samples and a corrupted first row, exit 0."""
    ref = cli("identify", "--data", str(robot_arm_path), *QUICK)
    assert ref.returncode == 0, ref.stderr
    piped = subprocess.run(
        f"cat {robot_arm_path} | {sys.executable} -m spm_sysid.apps.main identify "
        f"--data /dev/stdin {' '.join(QUICK)}", shell=True, capture_output=True, text=True,
        cwd=ROOT, timeout=300)
    assert piped.returncode == 0, piped.stderr
    subst = subprocess.run(
        ["bash", "-c", f"{sys.executable} -m spm_sysid.apps.main identify "
         f"--data <(cat {robot_arm_path}) {' '.join(QUICK)}"],
        capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert subst.returncode == 0, subst.stderr
    for r in (piped, subst):
        assert _model_lines(r.stdout) == _model_lines(ref.stdout)
        assert "1024 samples used" in r.stdout


def _model_lines(stdout: str) -> list[str]:
    """The equation and the criterion line without its timing."""
    return [ln.split(" samples, ")[0] for ln in stdout.splitlines()
            if ln.startswith(("y(t)", "criterion"))]


def test_devices_are_refused_at_once(tmp_path):
    with pytest.raises(DataError, match="character device, not a data file"):
        load_data("/dev/zero")
    r = cli("identify", "--data", "/dev/zero", *QUICK, timeout=60)
    assert r.returncode == 2 and "character device" in r.stderr and "Traceback" not in r.stderr
    link = tmp_path / "model.json"
    link.symlink_to("/dev/zero")
    with pytest.raises(ModelFormatError, match="character device"):
        NarxModel.load(link)
    r = cli("validate", str(link), timeout=60)
    assert r.returncode == 2 and "character device" in r.stderr


def test_utf8_byte_order_mark_keeps_the_time_column(robot_arm, tmp_path):
    """Excel's "CSV UTF-8": the BOM hid the time column (gaps fitted across)."""
    u, y = robot_arm
    rows = [f"{k * 0.01:.2f},{float(u[k])!r},{float(y[k])!r}" for k in range(200)
            if k not in (50, 51)]
    p = tmp_path / "excel.csv"
    p.write_bytes(b"\xef\xbb\xbf" + ("time,u,y\n" + "\n".join(rows) + "\n").encode())
    d = load_data(p)
    assert d.t is not None and len(d.t) == 198
    chosen = load_data(p, output="y")
    assert chosen.t is not None and np.ndim(chosen.u) == 1  # time is not an input
    np.testing.assert_array_equal(chosen.u, d.u)
    bare = tmp_path / "bare.csv"
    text = "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(u, y))
    bare.write_bytes(b"\xef\xbb\xbf" + text.encode())
    d = load_data(bare)
    assert len(d.u) == 1024 and d.u[0] == u[0]  # the first sample is kept


def test_truncated_gzip_is_corrupt_whatever_the_memory(robot_arm_path, tmp_path, monkeypatch):
    """Its size field is garbage (claims GBs): the memory guard must not answer."""
    good = gzip.compress(robot_arm_path.read_bytes())
    cut = good[: len(good) // 2] + b"\xff\xff\xff\xfe"  # a size field claiming ~4 GB
    (tmp_path / "trunc.dat.gz").write_bytes(cut)
    for limit in ("8G", "64M"):
        monkeypatch.setenv("SPM_SYSID_MAX_MEMORY", limit)
        with pytest.raises(DataError, match="not a readable gzip file"):
            load_data(tmp_path / "trunc.dat.gz")


def test_a_huge_field_is_one_clear_error(tmp_path):
    p = tmp_path / "wide.csv"
    p.write_text("u,y\n1,2\n" + "x" * 200_000 + ",3\n")
    with pytest.raises(DataError, match=r"line 3: 'xxxx.*200000 characters\) is not a number"):
        load_data(p)


# -- writing: regular files only, links followed, mounts written in place ------------------


def test_a_pipe_or_a_device_as_destination_is_refused_untouched(tmp_path):
    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    r = cli("identify", "--json", str(fifo), "--generations", "100000", timeout=60)
    assert r.returncode == 2 and "is a pipe, not a regular file" in r.stderr
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    dev = tmp_path / "null"
    try:
        os.mknod(dev, stat.S_IFCHR | 0o666, os.makedev(1, 3))  # what /dev/null is
    except PermissionError:
        pytest.skip("creating a device node needs root")
    for cmd in (["identify", "--generations", "100000"], ["certify", "--time-limit", "1"]):
        r = cli(*cmd, "--json", str(dev), timeout=60)
        assert r.returncode == 2 and "is a character device" in r.stderr, r.stderr
        assert stat.S_ISCHR(os.lstat(dev).st_mode)
    with pytest.raises(FileCheckError, match="character device"):
        atomic_write_text(dev, "{}")
    assert stat.S_ISCHR(os.lstat(dev).st_mode)


def test_a_symlink_destination_is_refused_by_the_commands_and_followed_by_the_library(
        tmp_path):
    """A command never writes through a link (it could name an input); the library may."""
    target = tmp_path / "real" / "model.json"
    target.parent.mkdir()
    target.write_text("old")
    link = tmp_path / "model.json"
    link.symlink_to(target)
    r = cli("identify", *QUICK, "--json", str(link))
    assert r.returncode == 2 and "is a symbolic link" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and target.read_text() == "old"
    assert link.is_symlink() and os.readlink(link) == str(target)
    dangling = tmp_path / "new.json"
    dangling.symlink_to(tmp_path / "real" / "fresh.json")
    atomic_write_text(dangling, "{}")
    assert dangling.is_symlink() and (tmp_path / "real" / "fresh.json").read_text() == "{}"


def test_a_bind_mounted_file_is_written_in_place(tmp_path):
    """docker -v model.json:/out/model.json: rename cannot replace a mount point."""
    if shutil.which("mount") is None:
        pytest.skip("no mount command")
    src, dst = tmp_path / "host.json", tmp_path / "container.json"
    src.write_text("old")
    dst.write_text("")
    if subprocess.run(["mount", "--bind", str(src), str(dst)],
                      capture_output=True).returncode != 0:
        pytest.skip("bind mounts need privileges this machine does not give")
    try:
        spare = tmp_path / "spare.json"
        spare.write_text("x")
        with pytest.raises(OSError):  # what failed after the whole search before
            os.replace(spare, dst)
        atomic_write_text(dst, '{"fresh": true}\n')
        assert json.loads(src.read_text()) == {"fresh": True}
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".container")]
    finally:
        subprocess.run(["umount", str(dst)], check=False)


def test_json_naming_the_data_file_is_refused(robot_arm_path, tmp_path):
    data = tmp_path / "take.dat"
    shutil.copy(robot_arm_path, data)
    before = data.read_bytes()
    r = cli("identify", "--data", str(data), "--json", str(data), "--generations", "100000")
    assert r.returncode == 2 and "it would be overwritten" in r.stderr
    assert data.read_bytes() == before


# -- model files that are not models ---------------------------------------------------------


@pytest.mark.parametrize("content, message", [
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    (None, "coefficients must be numbers, got 1000000000"),
    ("nan-metadata", "NaN is not a JSON number"),
])
def test_bad_model_files_are_one_error_line(tmp_path, content, message):
    doc = NarxModel(TermSpace(ny=1, nu=1, degree=1), [0, 1], np.array([0.5, 0.1])).to_dict()
    p = tmp_path / "m.json"
    if content is None:
        text = json.dumps(doc).replace("0.5", "1" + "0" * 400, 1)
    elif content == "nan-metadata":
        text = json.dumps({**doc, "metadata": {"x": float("nan")}})
    else:
        text = content
    p.write_text(text)
    with pytest.raises(ModelFormatError, match=message):
        NarxModel.load(p)
    r = cli("validate", str(p), timeout=60)
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


# -- batch and study inputs: names unique, settings checked, nothing overwritten -------------


def test_batch_model_names_never_collide():
    from spm_sysid.tools.batch import model_names

    names = model_names(["a/x.csv", "c/x.csv", "x-2.csv", "X.csv", "d/x.csv"])
    assert len({n.lower() for n in names}) == 5
    assert names[2] == "x-2" and names[0] == "x"  # an input's own stem is never taken


def test_batch_with_colliding_names_keeps_every_model(robot_arm_path, tmp_path):
    """a/x.csv, c/x.csv and x-2.csv gave two rows pointing at x-2.json: one model lost."""
    import csv

    for sub in ("a", "c"):
        (tmp_path / sub).mkdir()
        shutil.copy(robot_arm_path, tmp_path / sub / "x.dat")
    shutil.copy(robot_arm_path, tmp_path / "x-2.dat")
    inputs = [str(tmp_path / "a" / "x.dat"), str(tmp_path / "c" / "x.dat"),
              str(tmp_path / "x-2.dat")]
    r = cli("batch", *inputs, "--out", str(tmp_path / "out"), "--quiet", "--workers", "1",
            "--generations", "10", "--population-size", "20", "--seed", "1")
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(open(tmp_path / "out" / "summary.csv")))
    assert len({row["model"] for row in rows}) == 3
    assert all(os.path.exists(row["model"]) for row in rows)


@pytest.mark.parametrize("yaml_text, message", [
    ("default: [1, 2]\n", "'default' must map to settings"),
    ("1: {criterion: bic}\n", "the pattern 1 must be text"),
    ("default: {critrion: bic}\n", "unknown setting 'critrion' (did you mean 'criterion'?)"),
    ("default: {criterion: bic\n", "is not valid YAML (line 2"),
    ("- a\n- b\n", "expected a mapping of input patterns"),
])
def test_batch_settings_files_are_checked_before_any_work(robot_arm_path, tmp_path,
                                                           yaml_text, message):
    p = tmp_path / "per_input.yaml"
    p.write_text(yaml_text)
    r = cli("batch", str(robot_arm_path), "--out", str(tmp_path / "out"), "--settings", str(p),
            timeout=60)
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


@pytest.mark.parametrize("yaml_text, message", [
    ("runs: [1\n", "is not valid YAML (line 2"),
    ("populations: [20.9]\nruns: 1\n", "population_size must be an integer, got 20.9"),
    ("populations: [40, 40]\nruns: 1\n", "populations lists a value more than once"),
    ("criteria: [aic, aic]\nruns: 1\n", "criteria lists a value more than once"),
    ("[1, 2]\n", "expected a mapping of settings"),
])
def test_study_settings_are_checked_before_any_run(tmp_path, yaml_text, message):
    p = tmp_path / "study.yaml"
    p.write_text(yaml_text)
    r = cli("experiment", "--config", str(p), "--out", str(tmp_path / "out"), timeout=60)
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


# -- data that cannot identify, said so ---------------------------------------------------


@pytest.mark.parametrize("scale, word", [(1e-160, "RMS 2.8e-161"), (1e160, "RMS 2.8e+159")])
def test_magnitudes_beyond_double_precision_are_refused(robot_arm, scale, word):
    """1e-160 gave a one-term nonsense model with exit 0; 1e160 'linearly dependent'."""
    from spm_sysid import identify

    u, y = robot_arm
    with pytest.raises(DataError, match=re.escape(f"output y has {word}") + ".*rescale it"):
        identify(u=u * scale, y=y * scale)
    with pytest.raises(DataError, match="too far apart"):
        identify(u=u * 1e-200, y=y, term_space=TermSpace(degree=2))


@pytest.mark.parametrize("make_input, repeated", [
    (lambda u, y: np.full_like(u, 0.7), "u(t-2) is proportional to u(t-1)"),
    (lambda u, y: y.copy(), "u(t-1) is proportional to y(t-1)"),
])
def test_a_constant_or_repeated_input_leaves_an_output_only_model(robot_arm, tmp_path,
                                                                  make_input, repeated):
    """Both failed ('no structure could be fitted') though an output-only model exists."""
    from spm_sysid import GAConfig, identify

    u, y = robot_arm
    uu = make_input(u, y)
    res = identify(u=uu, y=y, seed=1, ga=GAConfig(generations=100))
    assert res.model.terms == ["y(t-1)", "y(t-2)", "y(t-3)", "y(t-4)"]
    assert res.ga.best_score == pytest.approx(-10472.75, abs=0.01)
    p = tmp_path / "d.dat"
    np.savetxt(p, np.column_stack([uu, y]))
    r = cli("identify", "--data", str(p), *QUICK)
    assert r.returncode == 0, r.stderr
    assert "repeat an earlier term on this data" in r.stdout and repeated in r.stdout


def test_zero_header_stamps_in_a_bag_use_the_log_time_and_say_so(robot_arm, tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer

    from spm_sysid.core.io import bagio

    u, y = robot_arm
    store = bagio.typestore()
    T = store.types
    zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    bag = tmp_path / "unstamped"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection(bagio.DEFAULT_INPUT_TOPIC, bagio.INPUT_TYPE, typestore=store)
        co = w.add_connection(bagio.DEFAULT_OUTPUT_TOPIC, bagio.OUTPUT_TYPE, typestore=store)
        for k in range(300):
            h = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=0,
                                                                               nanosec=0),
                                         frame_id="f")
            wr = T[bagio.INPUT_TYPE](header=h, wrench=T["geometry_msgs/msg/Wrench"](
                force=zero, torque=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=float(u[k]))))
            ac = T[bagio.OUTPUT_TYPE](header=h, accel=T["geometry_msgs/msg/Accel"](
                linear=T["geometry_msgs/msg/Vector3"](x=float(y[k]), y=0.0, z=0.0),
                angular=zero))
            t = 1_000_000_000 + k * 10_000_000
            w.write(ci, t, store.serialize_cdr(wr, bagio.INPUT_TYPE))
            w.write(co, t, store.serialize_cdr(ac, bagio.OUTPUT_TYPE))
    sig = bagio.read_bag_signals(bag)
    # the first message of each topic may be a real time 0; every repeat is not
    assert len(sig.y) == 300 and sig.unset_stamps == 598
    np.testing.assert_array_equal(sig.y, y[:300])
    r = cli("identify", "--bag", str(bag), *QUICK)
    assert r.returncode == 0, r.stderr
    assert "note: 598 message(s)" in r.stdout and "repeat header.stamp 0" in r.stdout
    assert "299 samples used" in r.stdout  # the sample at time 0 is a segment of its own
