"""Every file a command writes goes through one check, before the work: nothing is overwritten.

Not an input, not another output of the same run, not a link, a regular file or
absent, writable. ``--report`` and ``--json`` alike; ``batch`` writes only regular
files inside its folder.
"""

import json
import os
import subprocess
import sys

import pytest

from .conftest import ROOT

QUICK = ["--generations", "5", "--population-size", "20", "--seed", "1", "--quiet"]


def cli(*args, cwd=ROOT, timeout=300):
    return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                          capture_output=True, text=True, cwd=cwd, timeout=timeout)


@pytest.fixture
def take(robot_arm_path, tmp_path):
    path = tmp_path / "take.dat"
    path.write_bytes(robot_arm_path.read_bytes())
    return path


def _refused(r, *words):
    assert r.returncode == 2, r.stdout + r.stderr
    assert r.stderr.startswith("error: ") and "Traceback" not in r.stderr
    assert all(w in r.stderr for w in words), r.stderr
    assert "data:" not in r.stdout  # refused before the search, not after it


def test_a_report_through_a_link_to_the_data_is_refused(take, tmp_path):
    link = tmp_path / "link.html"
    link.symlink_to(take)
    before = take.read_bytes()
    _refused(cli("identify", "--data", str(take), "--report", str(link), *QUICK),
             "--report", "symbolic link")
    assert take.read_bytes() == before


def test_a_report_onto_the_json_the_data_or_the_model_is_refused(take, tmp_path):
    same = tmp_path / "same.html"
    _refused(cli("identify", "--data", str(take), "--json", str(same), "--report", str(same),
                 *QUICK), "the same file")
    data = tmp_path / "x.html"
    data.write_bytes(take.read_bytes())
    _refused(cli("identify", "--data", str(data), "--report", str(data), *QUICK),
             "is the input")
    assert data.read_bytes() == take.read_bytes()
    r = cli("identify", "--data", str(take), "--json", str(tmp_path / "m.html"), *QUICK)
    assert r.returncode == 0, r.stderr
    model = (tmp_path / "m.html").read_bytes()
    _refused(cli("validate", str(tmp_path / "m.html"), "--data", str(take), "--report",
                 str(tmp_path / "m.html")), "is the input")
    assert (tmp_path / "m.html").read_bytes() == model


def test_a_report_to_a_pipe_is_refused_not_a_hang(take, tmp_path):
    fifo = tmp_path / "f.html"
    os.mkfifo(fifo)
    _refused(cli("identify", "--data", str(take), "--report", str(fifo), *QUICK, timeout=60),
             "is a pipe")


def test_report_names_say_what_is_wrong(take, tmp_path):
    _refused(cli("identify", "--data", str(take), "--report", ".html", *QUICK),
             "has no file name")
    _refused(cli("identify", "--data", str(take), "--report", str(tmp_path / "r.txt"), *QUICK),
             "ending in .html (or .htm)")
    blocker = tmp_path / "file"
    blocker.write_text("")
    _refused(cli("identify", "--data", str(take), "--report", str(blocker / "r.html"),
                 *QUICK), "not a directory")
    r = cli("identify", "--data", str(take), "--report", str(tmp_path / "r.htm"), *QUICK)
    assert r.returncode == 0 and (tmp_path / "r.htm").stat().st_size > 100_000, r.stderr


def test_batch_replaces_links_in_its_folder_and_never_writes_through_them(robot_arm_path,
                                                                          tmp_path):
    a, b = tmp_path / "a.dat", tmp_path / "b.dat"
    a.write_bytes(robot_arm_path.read_bytes())
    b.write_bytes(robot_arm_path.read_bytes())
    out = tmp_path / "out"
    r = cli("batch", str(a), str(b), "--out", str(out), *QUICK)
    assert r.returncode == 0, r.stderr
    outside = {name: tmp_path / f"outside-{name}" for name in ("summary.csv", "a.json")}
    for name, target in outside.items():
        target.write_text("precious")
        (out / name).unlink()
        (out / name).symlink_to(target)
    r = cli("batch", str(a), "--out", str(out), "--force", *QUICK)
    assert r.returncode == 0, r.stderr
    for name, target in outside.items():
        assert target.read_text() == "precious"  # was overwritten through the link
        assert not (out / name).is_symlink() and (out / name).stat().st_size > 0
    # the earlier batch's b.json is gone, and the command says so: the summary lists a only
    assert not (out / "b.json").exists()
    assert "removed 1 model file(s) of the earlier batch" in r.stdout and "b.json" in r.stdout
    assert json.loads((out / ".spm_sysid_batch.json").read_text())["files"] == [
        "a.json", "summary.csv", "summary.md"]
