"""Without ROS: nothing hangs, crashes or is overwritten.

Each test is the failure as it was reported: a pipe given as a bag, a truncated
ahead-of-time build or numba cache, a batch writing over its own input, make-bag
deleting files that are not the bag's, a worker answering a job before it died.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from spm_sysid.core.errors import MemoryLimitError
from spm_sysid.core.memory import memory_limit

from .conftest import ROOT

BIN = Path(sys.executable).parent


def run(*args, env=None, timeout=120, cwd=None):
    """A command as a user types it; a hang fails the test (the timeout), it never blocks."""
    return subprocess.run([str(BIN / args[0]), *args[1:]], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=cwd)


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# -- a pipe as a bag ----------------------------------------------------------------------


def test_a_pipe_given_as_a_bag_is_one_error_line_and_never_blocks(tmp_path):
    fifo = tmp_path / "f.mcap"
    os.mkfifo(fifo)
    for given in (fifo, tmp_path / "g"):
        if given != fifo:
            os.mkfifo(given)
        r = run("spm-sysid", "identify", "--bag", str(given), timeout=60)
        assert r.returncode == 2, r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and "is a pipe, not a bag" in lines[0], r.stderr


def test_a_pipe_inside_a_bag_directory_is_refused(tmp_path):
    bag = tmp_path / "bag"
    assert run("spm-sysid", "make-bag", "--output", str(bag)).returncode == 0
    data = bag / "bag.mcap"
    data.unlink()
    os.mkfifo(data)
    r = run("spm-sysid", "identify", "--bag", str(bag), timeout=60)
    assert r.returncode == 2
    assert "bag.mcap is a pipe, not a bag file" in r.stderr


# -- the ahead-of-time build and numba's cache --------------------------------------------


def _aot_env(place: Path) -> dict:
    return {**os.environ, "SPM_SYSID_AOT_DIR": str(place)}


def _a_good_build(place: Path, env: dict) -> None:
    """The current build copied to ``place`` (``make setup`` made it), else built there.

    A copy saves a build of about 25 s of one core; the test builds once more anyway.
    """
    from spm_sysid.core.compiled.aot import build_status

    status = build_status()
    if status:
        place.mkdir(parents=True)
        for f in (status.path, status.path.with_name(status.path.name.split(".")[0] + ".json")):
            shutil.copy(f, place / f.name)
    else:
        assert run("spm-sysid", "compile", env=env, timeout=600).returncode == 0


@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                    reason="no C compiler: the kernels run on numba's JIT")
@pytest.mark.slow
@pytest.mark.timeout(1500)  # two builds of up to 600 s each on a busy machine
def test_a_truncated_build_runs_on_the_jit_with_one_warning_and_compile_repairs_it(tmp_path):
    env = _aot_env(tmp_path / "aot")
    _a_good_build(tmp_path / "aot", env)
    (lib,) = (tmp_path / "aot").glob("_aot_*.so")
    table = json.loads(lib.with_name(lib.name.split(".")[0] + ".json").read_text())
    assert table["size"] == lib.stat().st_size and table["sha256"] == digest(lib)
    good = run("spm-sysid", "identify", "--quiet", "--json", str(tmp_path / "good.json"),
               env=env)
    assert good.returncode == 0 and "warning" not in good.stderr
    lib.write_bytes(lib.read_bytes()[:100_000])  # as `head -c 100000` left it
    r = run("spm-sysid", "identify", "--quiet", "--json", str(tmp_path / "jit.json"), env=env)
    assert r.returncode == 0, r.stderr  # was SIGBUS (exit 135)
    warnings = [x for x in r.stderr.splitlines() if "warning" in x]
    assert len(warnings) == 1 and "is damaged" in warnings[0] and "compile" in warnings[0]
    doc = json.loads((tmp_path / "jit.json").read_text())
    assert doc["coefficients"] == json.loads((tmp_path / "good.json").read_text())[
        "coefficients"]
    c = run("spm-sysid", "compile", env=env, timeout=600)
    assert c.returncode == 0, c.stderr
    (lib,) = (tmp_path / "aot").glob("_aot_*.so")  # whole again, as its table says
    table = json.loads(lib.with_name(lib.name.split(".")[0] + ".json").read_text())
    assert table["size"] == lib.stat().st_size > 100_000 and table["sha256"] == digest(lib)
    again = run("spm-sysid", "identify", "--quiet", env=env)
    assert again.returncode == 0 and "warning" not in again.stderr


KERNEL_MODULE = '''
import numpy as np
from spm_sysid.core.compiled.registry import jit


@jit
def total(x):
    s = 0.0
    for v in x:
        s += v
    return s


print(total(np.arange(10.0)))
'''


@pytest.mark.slow
def test_an_unreadable_numba_cache_entry_is_compiled_again(tmp_path):
    (tmp_path / "kern.py").write_text(KERNEL_MODULE)
    env = {**os.environ, "SPM_SYSID_AOT": "0", "PYTHONPATH": f"{tmp_path}:{ROOT}"}
    env.pop("NUMBA_CACHE_DIR", None)

    def call():
        return subprocess.run([sys.executable, "-c", "import kern"], capture_output=True,
                              text=True, env=env, cwd=tmp_path, timeout=300)

    first = call()
    assert first.returncode == 0 and first.stdout.strip() == "45.0", first.stderr
    cached = sorted((tmp_path / "__pycache__").glob("kern.total-*.nb*"))
    assert {p.suffix for p in cached} == {".nbi", ".nbc"}
    for kind in (".nbi", ".nbc"):  # a truncated index, then a truncated data file
        for p in (tmp_path / "__pycache__").glob(f"kern.total-*{kind}"):
            p.write_bytes(p.read_bytes()[:20])
        r = call()
        assert r.returncode == 0 and r.stdout.strip() == "45.0", r.stderr  # was UnpicklingError
        warnings = [x for x in r.stderr.splitlines() if "warning" in x]
        assert len(warnings) == 1 and "cannot be read" in warnings[0], r.stderr
        again = call()  # the entry was written anew
        assert again.returncode == 0 and "warning" not in again.stderr


CALLER_MODULE = """
from spm_sysid.core.compiled.registry import jit_exact
from callee import scale


@jit_exact
def caller(x):
    return scale(x)


print(caller(2.0), sum(caller.jit.stats.cache_hits.values()))
"""

CALLEE_MODULE = """
from spm_sysid.core.compiled.registry import jit_exact


@jit_exact
def scale(x):
    return {factor} * x
"""


@pytest.mark.slow
def test_a_cached_kernel_is_compiled_again_when_a_kernel_module_changes(tmp_path):
    """numba renews a cache entry when its own function's file changes, not when a kernel
    it calls in another module does: a caller compiled with the old callee would run it.
    The entries are keyed by the kernel sources' hash, so a change there compiles again."""
    (tmp_path / "callee.py").write_text(CALLEE_MODULE.format(factor=3.0))
    (tmp_path / "caller.py").write_text(CALLER_MODULE)
    env = {**os.environ, "SPM_SYSID_AOT": "0", "PYTHONPATH": f"{tmp_path}:{ROOT}"}
    env.pop("NUMBA_CACHE_DIR", None)

    def call(sources: str) -> tuple[float, int]:
        code = ("from spm_sysid.core.compiled import registry\n"
                f"registry.source_hash = lambda: {sources!r}\nimport caller")
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           env=env, cwd=tmp_path, timeout=300)
        assert r.returncode == 0, r.stderr
        value, hits = r.stdout.split()
        return float(value), int(hits)

    assert call("first sources") == (6.0, 0)   # compiled and cached
    assert call("first sources") == (6.0, 1)   # loaded from the cache
    (tmp_path / "callee.py").write_text(CALLEE_MODULE.format(factor=5.0))
    assert call("second sources") == (10.0, 0)  # the sources changed: compiled anew
    assert call("second sources") == (10.0, 1)


def test_no_writable_cache_location_compiles_in_memory_with_one_warning(monkeypatch, capsys):
    from numba.core.caching import CacheImpl

    from spm_sysid.core.compiled import registry as compiled

    # what numba meets on a read-only install with no writable home (cannot be made here
    # as root): no cache locator accepts the file
    monkeypatch.setattr(CacheImpl, "_locator_classes", [])
    monkeypatch.setattr(compiled, "_warned", set())
    kernel = compiled.Kernel(lambda x: x + 1.0, fastmath=False)
    assert kernel.jit(1.0) == 2.0
    err = capsys.readouterr().err
    assert err.count("spm_sysid: warning") == 1 and "cannot cache the compiled kernels" in err


# -- batch and make-bag never write over what is not theirs -------------------------------


def _bytes(folder: Path) -> dict:
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def test_batch_never_writes_over_an_unrelated_file(robot_arm_path, tmp_path):
    d = tmp_path / "d"
    d.mkdir()
    shutil.copy(robot_arm_path, d / "take.csv")
    (d / "take.json").write_text('{"mine": true}\n')
    before = _bytes(d)
    r = run("spm-sysid", "batch", str(d / "take.csv"), "--out", str(d))
    assert r.returncode != 0
    assert "take.json exists and no earlier batch wrote it" in r.stderr
    assert _bytes(d) == before
    r = run("spm-sysid", "batch", str(d / "take.csv"), "--out", str(d), "--force")
    assert r.returncode != 0 and _bytes(d) == before  # --force does not change that


@pytest.mark.parametrize("name", ["run.json", "summary.csv"])
def test_batch_never_writes_over_its_input(robot_arm_path, tmp_path, name):
    d = tmp_path / "d"
    d.mkdir()
    shutil.copy(robot_arm_path, d / name)
    before = _bytes(d)
    for extra in ([], ["--force"]):
        r = run("spm-sysid", "batch", str(d / name), "--out", str(d), *extra)
        assert r.returncode != 0 and "it is one of the inputs" in r.stderr, r.stderr
        assert _bytes(d) == before


def test_batch_replaces_only_its_own_earlier_files_with_force(robot_arm_path, tmp_path):
    out = tmp_path / "out"
    assert run("spm-sysid", "batch", str(robot_arm_path), "--out", str(out)).returncode == 0
    manifest = json.loads((out / ".spm_sysid_batch.json").read_text())
    assert set(manifest["files"]) == {"robot_arm.json", "summary.csv", "summary.md"}
    (out / "notes.txt").write_text("keep me\n")
    r = run("spm-sysid", "batch", str(robot_arm_path), "--out", str(out))
    assert r.returncode != 0 and "holds an earlier batch" in r.stderr and "--force" in r.stderr
    r = run("spm-sysid", "batch", str(robot_arm_path), "--out", str(out), "--force")
    assert r.returncode == 0, r.stderr
    assert (out / "notes.txt").read_text() == "keep me\n"


def test_make_bag_force_keeps_files_that_are_not_the_bags(tmp_path):
    bag = tmp_path / "bag"
    assert run("spm-sysid", "make-bag", "--output", str(bag)).returncode == 0
    for name in ("other.mcap", "old.db3"):
        (bag / name).write_bytes(b"not the bag's")
    r = run("spm-sysid", "make-bag", "--output", str(bag), "--force")
    assert r.returncode != 0 and "not part of the bag" in r.stderr
    assert (bag / "other.mcap").read_bytes() == b"not the bag's"
    assert (bag / "old.db3").read_bytes() == b"not the bag's"


def test_make_bag_force_through_a_symlink_replaces_the_bag_and_keeps_the_link(tmp_path):
    real = tmp_path / "real"
    assert run("spm-sysid", "make-bag", "--output", str(real)).returncode == 0
    link = tmp_path / "link"
    link.symlink_to(real)
    r = run("spm-sysid", "make-bag", "--output", str(link), "--force", "--rate", "50")
    assert r.returncode == 0, r.stderr
    assert link.is_symlink() and Path(os.readlink(link)) == real
    import yaml

    info = yaml.safe_load((real / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["duration"]["nanoseconds"] == 1023 * 20_000_000  # 50 Hz, the new bag's rate
    assert not [p for p in tmp_path.iterdir() if ".old-" in p.name or ".partial-" in p.name]


# -- settings from the environment ----------------------------------------------------------


@pytest.mark.parametrize("text", ["inf", "1e400", "unlimited"])
def test_an_unlimited_memory_bound_is_no_bound(monkeypatch, text):
    monkeypatch.setenv("SPM_SYSID_MAX_MEMORY", text)
    limit, source = memory_limit()
    assert limit >= 2**60 and source == "SPM_SYSID_MAX_MEMORY"


@pytest.mark.parametrize("text, words", [("0.5", "less than one byte"),
                                         ("0", "must be positive"), ("nan", "not a size"),
                                         ("lots", "not a size")])
def test_a_memory_bound_that_means_nothing_is_a_clear_error(monkeypatch, text, words):
    monkeypatch.setenv("SPM_SYSID_MAX_MEMORY", text)
    with pytest.raises(MemoryLimitError, match=words):
        memory_limit()


def test_a_set_memory_bound_counts_what_the_process_holds(monkeypatch, robot_arm):
    """SPM_SYSID_MAX_MEMORY is the most the process may hold: the matrix comes on top."""
    from spm_sysid.core.fit.problem import Problem
    from spm_sysid.core.memory import check_memory, resident_bytes
    from spm_sysid.core.model.terms import TermSpace

    held = resident_bytes()
    assert held > 10 * 2**20  # an interpreter with numpy: tens of MB at least
    monkeypatch.setenv("SPM_SYSID_MAX_MEMORY", str(held + 2**22))
    check_memory(2**23, "eight megabytes", held=False)  # the new need alone fits
    with pytest.raises(MemoryLimitError, match=r"eight megabytes would need about 8.0 MB "
                                               r"besides the .* this process holds"):
        check_memory(2**23, "eight megabytes", held=True)
    monkeypatch.setenv("SPM_SYSID_MAX_MEMORY", str(held + 2**20))
    u, y = robot_arm  # its (3, 3, 2) problem: 0.2 MB of matrix and five slices of it
    with pytest.raises(MemoryLimitError, match="1021 rows x 27 candidate terms would need "
                                               "about .* besides the"):
        Problem.from_signals(u, y, TermSpace(ny=3, nu=3, degree=2))
    monkeypatch.setenv("SPM_SYSID_MAX_MEMORY", str(held + 2**30))
    assert Problem.from_signals(u, y, TermSpace(ny=3, nu=3, degree=2)).rows == 1021
    monkeypatch.delenv("SPM_SYSID_MAX_MEMORY")  # the default: half of the room left
    assert Problem.from_signals(u, y, TermSpace(ny=3, nu=3, degree=2)).rows == 1021


def test_identify_and_validate_with_an_unlimited_memory_bound(tmp_path):
    env = {**os.environ, "SPM_SYSID_MAX_MEMORY": "inf"}
    r = run("spm-sysid", "identify", "--quiet", "--json", str(tmp_path / "m.json"), env=env)
    assert r.returncode == 0, r.stderr  # was OverflowError
    r = run("spm-sysid", "validate", str(tmp_path / "m.json"), env=env)
    assert r.returncode == 0, r.stderr


# -- a study or batch in this process stops on Ctrl-C ------------------------------------


def test_an_interrupt_a_task_swallows_still_stops_the_job_before_the_next():
    """The runner's mark: a KeyboardInterrupt lost inside a task (caught by a library,
    or raised in a finaliser, where Python prints and drops it) still stops the job."""
    import signal

    from spm_sysid.tools.runner import run_tasks

    # Python's own handler, whatever the test runner's worker process installed
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    ran = []

    def task(t, shared):
        ran.append(t)
        if t == 1:
            try:
                signal.raise_signal(signal.SIGINT)
            except KeyboardInterrupt:
                pass  # lost here
        return t

    try:
        with pytest.raises(KeyboardInterrupt):
            run_tasks(task, {str(i): i for i in range(4)}, workers=1)
        assert ran == [0, 1]  # task 1 finished, task 2 never started
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
        ran.clear()  # without an interrupt every task runs
        assert [o.result for o in run_tasks(lambda t, s: t, {"a": 5, "b": 6},
                                            workers=1).values()] == [5, 6]
    finally:
        signal.signal(signal.SIGINT, previous)


# -- the node's worker: a job after a cancel goes to a live process ------------------------


def test_a_job_submitted_when_one_is_canceled_goes_to_the_new_worker():
    from spm_sysid.ros.worker import JobCancelledError, JobWorker

    worker = JobWorker("test.helpers.jobs:sleepy",
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert worker.wait_ready(120)
        second, submitted = [], threading.Event()

        def resubmit(job):  # the node starts the next goal from the answer of the last
            second.append(worker.submit(0.01))
            submitted.set()

        for _ in range(10):  # failed 10 of 10 before: the dying worker got the job
            second.clear()
            submitted.clear()
            first = worker.submit(60.0)
            first.add_done_callback(resubmit)
            threading.Timer(0.2, worker.cancel, args=("job_timeout",)).start()
            with pytest.raises(JobCancelledError):
                first.result(timeout=60)
            assert submitted.wait(60)
            assert second[0].result(timeout=120) == 0.01
    finally:
        worker.close()


def test_a_worker_started_from_a_thread_that_ends_lives_on():
    """Linux sends the parent-death signal when the *thread* that started a child ends.

    The workers ask for SIGKILL when their parent dies; one started by a cancel on a
    timer's thread (a job timeout) or by a dead worker's reader thread was killed as
    soon as that thread returned, if it had asked by then (CI, 2026-12-07: the job
    after a cancel died with SIGKILL). Here the thread waits until the new worker is
    ready, so it has asked, and then ends.
    """
    from spm_sysid.ros.worker import JobCancelledError, JobWorker

    worker = JobWorker("test.helpers.jobs:sleepy", env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert worker.wait_ready(120)
        first = worker.submit(60.0)

        def cancel_then_wait():
            worker.cancel("job_timeout")  # starts the new worker (from this thread)
            assert worker.wait_ready(120)  # it has asked for its parent-death signal

        thread = threading.Thread(target=cancel_then_wait)
        thread.start()
        thread.join()
        with pytest.raises(JobCancelledError):
            first.result(timeout=60)
        pid = worker.pid
        deadline = time.monotonic() + 2.0  # a SIGKILL at the thread's end arrives at once
        while time.monotonic() < deadline and worker.pid == pid and worker.ready:
            time.sleep(0.05)
        assert worker.pid == pid and worker.ready, "the worker died with its thread"
        assert worker.submit(0.01).result(timeout=120) == 0.01
    finally:
        worker.close()


def test_a_worker_that_dies_while_starting_backs_off_and_says_why(tmp_path):
    from spm_sysid.ros.worker import JobWorker

    events = []
    worker = JobWorker("test.helpers.no_such_module:job", on_event=events.append,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        deadline = time.monotonic() + 60
        while sum("next try in" in e for e in events) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        tries = [e for e in events if "next try in" in e]
        # backing off, 1 s then 2 s (it was restarted about four times a second)
        assert tries[0].endswith("next try in 1 s") and tries[1].endswith("next try in 2 s")
        assert "died while starting" in worker.start_failure
        assert "ModuleNotFoundError" in worker.start_failure  # its last stderr line
        assert not worker.ready
    finally:
        worker.close()


def test_progress_lines_say_only_what_means_something():
    from spm_sysid.core.progress import Progress

    assert Progress("validation", elapsed=0.3).line() == "validation, 0.3 s"  # was ": 0, 0 ..."
    assert Progress("checking data").line() == "checking data, 0.0 s"
    assert Progress("search", 120, 300, -10744.781, 21805, elapsed=0.31).line() == \
        "search: generation 120/300, best -10744.78, 21805 structures fitted, 0.3 s"
    assert Progress("certification", 7, 0, -5.0, 10, -6.5, 1.0).line() == \
        ("certification: node 7, best -5.00, lower bound -6.50 (gap 1.50), 10 structures "
         "fitted, 1.0 s")


# -- crafted model documents, stuck signals, names, plots, tracking -------------------------


@pytest.fixture(scope="module")
def arm_doc(robot_arm):
    from spm_sysid.core.jobs import JobSettings, run_job
    from spm_sysid.core.record import Record

    u, y = robot_arm
    record = Record.from_samples(u, y, source="robot arm")
    result = run_job(record, JobSettings.from_values({"seed": 1}))
    return result.model.to_dict(), result.residuals


@pytest.mark.parametrize("edit, words", [
    (lambda d: d.__setitem__("schema_version", True), "schema version True"),
    (lambda d: d.__setitem__("n_samples", -5), "'n_samples' must be a number >= 0"),
    (lambda d: d["uncertainty"]["covariance"][0].__setitem__(0, -1.0),
     "negative variance"),
    (lambda d: d["uncertainty"].__setitem__("sigma2", -1.0), "sigma2 must be"),
])
def test_a_crafted_model_document_is_refused_with_its_reason(arm_doc, tmp_path, edit, words):
    import copy

    doc = copy.deepcopy(arm_doc[0])
    edit(doc)
    path = tmp_path / "m.json"
    path.write_text(json.dumps(doc))
    r = run("spm-sysid", "validate", str(path))
    assert r.returncode == 2 and words in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_the_tracker_never_overflows_on_huge_coefficients(arm_doc):
    import copy

    from spm_sysid.core.model.narx import NarxModel
    from spm_sysid.core.online.session import OnlineSession

    doc = copy.deepcopy(arm_doc[0])
    doc["coefficients"] = [1e300] * len(doc["coefficients"])
    model = NarxModel.from_dict(doc)
    with pytest.raises(ValueError, match="too large to track"):
        OnlineSession(model, tracking=True, sample_period=0.01)


def test_a_constant_output_is_not_identifiable(robot_arm, tmp_path):
    u, _ = robot_arm
    path = tmp_path / "stuck.dat"
    np.savetxt(path, np.column_stack([u, np.full(len(u), 0.25)]))
    r = run("spm-sysid", "identify", "--data", str(path))
    assert r.returncode == 2
    assert "the output y is constant (0.25 throughout; a stuck or disconnected sensor?)" \
        in r.stderr


def test_validate_reads_the_columns_the_model_was_identified_on(robot_arm, tmp_path):
    u, y = robot_arm
    path = tmp_path / "named.csv"
    # the output first: a file read in the default layout would swap them
    np.savetxt(path, np.column_stack([y, u]), delimiter=",", header="acc,tau", comments="")
    model = tmp_path / "m.json"
    r = run("spm-sysid", "identify", "--data", str(path), "--inputs", "tau", "--output", "acc",
            "--quiet", "--json", str(model))
    assert r.returncode == 0, r.stderr
    r = run("spm-sysid", "validate", str(model), "--data", str(path))
    assert r.returncode == 0, r.stderr
    assert "columns chosen by the model's signal names: inputs tau, output acc" in r.stdout
    assert "fit 98.14 %" in r.stdout  # the paper's eq. (1) on its own data


def test_columns_that_differ_only_by_case_stay_apart(robot_arm, tmp_path):
    from spm_sysid.core.io.data import load_data

    u, y = robot_arm
    path = tmp_path / "joints.csv"
    np.savetxt(path, np.column_stack([u, y, 2 * y]), delimiter=",", header="tau1,q1,Q1",
               comments="")
    data = load_data(path, inputs=["tau1"], output=["q1", "Q1"])
    assert data.output_names == ("q1", "Q1")
    np.testing.assert_array_equal(data.y[:, 1], 2 * y)


def test_more_lags_than_inputs_names_the_inputs():
    from spm_sysid.core.model.terms import TermSpace

    with pytest.raises(ValueError, match=r"nu gives 2 values, but there is 1 input \(tau1\)"):
        TermSpace(nu=(1, 1), inputs=("tau1",), output="q1")


def test_too_few_rows_to_validate_says_so(robot_arm, tmp_path):
    u, y = robot_arm
    path = tmp_path / "short.dat"
    np.savetxt(path, np.column_stack([u[:12], y[:12]]))
    r = run("spm-sysid", "identify", "--data", str(path), "--ny", "1", "--nu", "1",
            "--degree", "1")
    assert r.returncode == 2
    assert "too few samples to validate with --correlation-lags 20: 11 validation rows" \
        in r.stderr


def test_figures_have_a_time_axis_when_the_data_have_stamps(robot_arm, tmp_path):
    from spm_sysid.core.record import Record

    u, y = robot_arm
    record = Record.from_samples(u, y, source="x", stamps_ns=np.arange(len(y)) * 10_000_000)
    seconds = record.row_seconds([(0, len(y))], 4)
    assert len(seconds) == len(y) - 4 and seconds[0] == pytest.approx(0.04)
    assert Record.from_samples(u, y, source="x").row_seconds([(0, len(y))], 4) is None
    bag = tmp_path / "bag"
    assert run("spm-sysid", "make-bag", "--output", str(bag), "--rate", "100").returncode == 0
    r = run("spm-sysid", "identify", "--bag", str(bag), "--quiet", "--plots",
            str(tmp_path / "figs"))
    assert r.returncode == 0, r.stderr
    svg = (tmp_path / "figs" / "model_one_step.svg").read_text()
    assert "time (s)" in svg and ">sample<" not in svg


def test_tracking_from_a_constant_input_never_drifts(arm_doc):
    import copy

    from spm_sysid.core.model.narx import NarxModel
    from spm_sysid.core.online.session import OnlineSession

    doc = copy.deepcopy(arm_doc[0])
    assert doc["metadata"]["monitor"]["input_std"] > 0  # the identification's input spread
    model = NarxModel.from_dict(doc)
    session = OnlineSession(model, tracking=True, sample_period=0.01)
    rng = np.random.default_rng(0)
    y = [0.0] * 4
    for k in range(2000):  # the input constant from the first sample, the output noise
        y.append(0.001 * rng.standard_normal())
        session.feed(k * 10_000_000, 0.3, y[-1])
    tracker = session.tracker
    assert tracker.updates == 0 and tracker.frozen > 0  # was 499 updates, 2.7 SE of drift
    np.testing.assert_array_equal(tracker.theta, model.coefficients)


def test_the_nodes_worker_runs_a_real_job_and_relays_its_progress(robot_arm):
    """The records carry a builder of the best model (for Ctrl-C), local to the
    worker: they still cross the pipe (this failed every identification of the node)."""
    import pickle

    from spm_sysid.core.jobs import JobSettings
    from spm_sysid.core.progress import Progress
    from spm_sysid.core.record import Record
    from spm_sysid.ros.worker import JobWorker

    record = Progress("validation", 3, 5, best=-2.0, bound=-3.0, elapsed=1.0,
                      best_model=lambda: "a model")
    copy = pickle.loads(pickle.dumps(record))
    assert copy == record and copy.best_model is None
    phases = []
    worker = JobWorker("spm_sysid.core.jobs.run:run_job",
                       on_progress=lambda p: phases.append(p.phase))
    try:
        assert worker.wait_ready(120)
        u, y = robot_arm
        result = worker.submit(Record.from_samples(u, y, source="arm"),
                               JobSettings.from_values({"seed": 1})).result(timeout=600)
        assert len(result.model.terms) > 0
        assert {"search", "validation"} <= set(phases)
    finally:
        worker.close()
