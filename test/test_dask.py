"""Studies and batches on a real Dask cluster: a scheduler and two worker processes."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from .conftest import ROOT

BIN = os.path.dirname(sys.executable)


#: one worker runs this file (its module fixture is expensive to make twice)
#: a study may wait 600 s for its runs on a busy machine: the limit says so
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("dask"), pytest.mark.timeout(900)]


def _scheduler_address(sched_file, log, limit: float = 120.0) -> str:
    """The address in the scheduler's file, once written whole (the scheduler creates
    the file before it writes it: on a busy machine it was read empty)."""
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        try:
            return json.loads(sched_file.read_text())["address"]
        except (OSError, ValueError, KeyError):
            time.sleep(0.2)
    pytest.fail(f"the dask scheduler wrote no address in {limit:.0f} s: {log.read_text()[-500:]}")


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """`dask scheduler` and two `dask worker` processes on 127.0.0.1."""
    pytest.importorskip("distributed")
    d = tmp_path_factory.mktemp("dask")
    sched_file = d / "scheduler.json"
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    procs = [subprocess.Popen([f"{BIN}/dask", "scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--no-dashboard", "--scheduler-file", str(sched_file)],
                              stdout=subprocess.DEVNULL, stderr=open(d / "sched.log", "w"),
                              env=env)]
    workers: list = []

    def start_worker(i):
        p = subprocess.Popen([f"{BIN}/dask", "worker", address, "--nworkers", "1",
                              "--nthreads", "1", "--no-dashboard", "--host", "127.0.0.1"],
                             stdout=subprocess.DEVNULL,
                             stderr=open(d / f"worker{i}.log", "w"), env=env, cwd=ROOT)
        workers.append(p)
        return p

    try:  # the processes end even when the set-up fails (one was left running)
        address = _scheduler_address(sched_file, d / "sched.log")
        start_worker(0)
        start_worker(1)
        from distributed import Client

        with Client(address, timeout=60) as c:
            c.wait_for_workers(2, timeout=120)
        yield {"address": address, "workers": workers, "start_worker": start_worker}
    finally:
        for p in workers + procs:
            p.terminate()
        for p in workers + procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()

def spm(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", *args],
                          capture_output=True, text=True, cwd=ROOT, timeout=timeout)


STUDY = ("experiment", "--criteria", "aic,bic", "--populations", "40", "--spm", "0,0.15",
         "--runs", "3", "--generations", "40", "--seed", "3", "--quiet")


def _runs(out):
    runs = json.loads((out / "runs.json").read_text())["runs"]
    return [(r["criterion"], r["population_size"], r["spm_fraction"], r["run"], r["terms"],
             round(r["final_value"], 6), r["best_curve"]) for r in runs]


def test_study_on_the_cluster_equals_the_local_study(cluster, tmp_path):
    local = spm(*STUDY, "--out", str(tmp_path / "local"))
    assert local.returncode == 0, local.stderr
    remote = spm(*STUDY, "--out", str(tmp_path / "dask"), "--scheduler", cluster["address"])
    assert remote.returncode == 0, remote.stderr
    assert f"running on the Dask cluster at {cluster['address']}" in remote.stdout
    assert _runs(tmp_path / "dask") == _runs(tmp_path / "local")  # same seeds, same runs
    assert len(_runs(tmp_path / "local")) == 12


def test_a_worker_killed_mid_study_loses_no_run(cluster, tmp_path):
    out = tmp_path / "killed"
    args = [sys.executable, "-m", "spm_sysid.apps.main", *STUDY[:-1], "--runs", "6",
            "--generations", "150", "--out", str(out), "--scheduler", cluster["address"]]
    study = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    partial = out / "runs.partial.jsonl"
    deadline = time.monotonic() + 120
    while (not partial.exists() or len(partial.read_text().splitlines()) < 2) \
            and time.monotonic() < deadline:
        time.sleep(0.1)
    victim = cluster["workers"][0]
    os.kill(victim.pid, signal.SIGKILL)  # a worker dies with runs on it
    cluster["start_worker"](2)  # (the cluster of the next tests has two again)
    stdout, stderr = study.communicate(timeout=600)
    assert study.returncode == 0, stderr
    runs = json.loads((out / "runs.json").read_text())["runs"]
    assert len(runs) == 24 and len({(r["criterion"], r["spm_fraction"], r["run"])
                                    for r in runs}) == 24


def test_an_interrupted_study_resumes_without_redoing_runs(cluster, tmp_path):
    out = tmp_path / "resume"
    # runs of about 0.5 s each (the study's 12 runs of 40 generations took 0.2 s in all, and
    # with runs of 0.2 s a busy machine let the worker finish all twelve while the parent,
    # short of CPU, had written two lines: they all finished before the interrupt arrived);
    # 24 of them: a fresh-clone CI run (2026-12-05) still finished all 12 of 0.5 s after
    # the third line, so the interrupt has 21 runs (about 10 s) to arrive in
    study_args = (*STUDY[:-1], "--runs", "6", "--generations", "2500", "--quiet")
    args = [sys.executable, "-m", "spm_sysid.apps.main", *study_args, "--out", str(out),
            "--workers", "1"]
    study = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    partial = out / "runs.partial.jsonl"
    deadline = time.monotonic() + 120
    while (not partial.exists() or len(partial.read_text().splitlines()) < 3) \
            and time.monotonic() < deadline:
        time.sleep(0.05)
    study.send_signal(signal.SIGINT)
    study.wait(60)
    done = len([line for line in partial.read_text().splitlines() if line.strip()])
    assert 3 <= done < 24
    again = spm(*study_args, "--out", str(out))
    assert again.returncode == 2 and "--resume" in again.stderr  # nothing overwritten
    resumed = spm(*study_args, "--out", str(out), "--resume", "--scheduler",
                  cluster["address"])
    assert resumed.returncode == 0, resumed.stderr
    assert f"resumed: {done} run(s) were already done" in resumed.stdout
    ref = spm(*study_args, "--out", str(tmp_path / "ref"))
    assert ref.returncode == 0, ref.stderr
    assert _runs(out) == _runs(tmp_path / "ref")


def test_batch_on_the_cluster_reports_a_broken_file_and_finishes_the_rest(cluster, tmp_path,
                                                                          robot_arm_path):
    import numpy as np

    rng = np.random.default_rng(1)
    u = rng.uniform(-1, 1, 400)
    y = np.zeros(400)
    for t in range(2, 400):
        y[t] = 0.6 * y[t - 1] - 0.2 * y[t - 2] + 0.8 * u[t - 1] + 0.1 * y[t - 1] * u[t - 1]
    np.savetxt(tmp_path / "take2.dat", np.column_stack([u, y + 1e-3 * rng.standard_normal(400)]))
    (tmp_path / "broken.dat").write_text("1 2\n3 x\n")
    inputs = [str(robot_arm_path), str(tmp_path / "take2.dat"), str(tmp_path / "broken.dat")]
    common = ("--criterion", "bic", "--seed", "1", "--quiet")
    local = spm("batch", *inputs, "--out", str(tmp_path / "local"), *common)
    remote = spm("batch", *inputs, "--out", str(tmp_path / "dask"), *common,
                 "--scheduler", cluster["address"])
    for r in (local, remote):
        assert r.returncode == 1 and "1 input(s) failed" in r.stderr
        assert "2 of 3 input(s) identified" in r.stdout
    import csv

    rows = {k: list(csv.DictReader(open(tmp_path / k / "summary.csv"))) for k in ("local",
                                                                                   "dask")}
    for k in rows:
        assert [r["status"] for r in rows[k]][:2] == ["ok", "ok"]
        assert rows[k][2]["status"].startswith("error: DataError") and "'x'" in \
            rows[k][2]["status"]
    assert [r["value"] for r in rows["local"]] == [r["value"] for r in rows["dask"]]
    assert rows["local"][0]["value"].startswith("-10707.48")  # the paper's eq. (2)
    m = json.loads((tmp_path / "dask" / "robot_arm.json").read_text())
    assert len(m["terms"]) == 7 and (tmp_path / "dask" / "take2.json").exists()


# -- issue 17: jobs that keep to themselves; deadlines; files on the client ----------------


def _take(path, n, seed, a):
    """A record of y(t) = a y(t-1) + 0.5 u(t-1) + noise (its own data, its own model)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, n)
    y = np.zeros(n)
    for t in range(1, n):
        y[t] = a * y[t - 1] + 0.5 * u[t - 1]
    np.savetxt(path, np.column_stack([u, y + 1e-3 * rng.standard_normal(n)]))


def test_two_jobs_at_once_on_one_cluster_each_get_their_own_results(cluster, tmp_path):
    """Keys were the same for every job: the second reported the first one's results."""
    import csv

    for job, (n, a) in {"one": (600, 0.3), "two": (1024, 0.8)}.items():
        (tmp_path / job).mkdir()
        for k in range(3):  # the same file names in both jobs (the same task keys before)
            _take(tmp_path / job / f"take{k}.dat", n, seed=k, a=a)
    common = ["--criterion", "bic", "--seed", "1", "--quiet", "--ny", "1", "--nu", "1",
              "--validation", "none", "--generations", "30", "--population-size", "30",
              "--scheduler", cluster["address"]]
    procs = {job: subprocess.Popen(
        [sys.executable, "-m", "spm_sysid.apps.main", "batch",
         *[str(tmp_path / job / f"take{k}.dat") for k in range(3)],
         "--out", str(tmp_path / f"out-{job}"), *common], cwd=ROOT, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True) for job in ("one", "two")}
    for p in procs.values():
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    for job, (n, a) in {"one": (600, 0.3), "two": (1024, 0.8)}.items():
        rows = list(csv.DictReader(open(tmp_path / f"out-{job}" / "summary.csv")))
        assert [int(r["samples"]) for r in rows] == [n] * 3
        for r in rows:
            m = json.loads(open(r["model"]).read())
            coef = dict(zip(m["terms"], m["coefficients"]))
            assert abs(coef["y(t-1)"] - a) < 0.01 and abs(coef["u(t-1)"] - 0.5) < 0.01


def test_a_scheduler_address_that_is_not_dask_fails_within_the_deadline(tmp_path):
    """A web server at the port: the command hung (still running at 580 s)."""
    import http.server
    import threading

    import spm_sysid.tools.runner as runner

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    address = f"tcp://127.0.0.1:{server.server_address[1]}"
    try:
        with pytest.raises(RuntimeError, match="not a Dask scheduler"):
            runner.check_scheduler(address, timeout=3)
        env = {**os.environ, "SPM_SYSID_DASK_CONNECT_TIMEOUT": "4"}
        r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "batch",
                            str(tmp_path / "none.dat"), "--out", str(tmp_path / "o"),
                            "--scheduler", address], capture_output=True, text=True, cwd=ROOT,
                           timeout=120, env=env)
        assert r.returncode == 2 and "no Dask scheduler answered" in r.stderr, r.stderr
        assert "within 4 s" in r.stderr
    finally:
        server.shutdown()
        server.server_close()


def test_batch_models_are_written_where_the_client_asked(cluster, tmp_path, robot_arm_path):
    """Workers run in another directory (another machine): the client writes the files."""
    client_dir = tmp_path / "client"
    client_dir.mkdir()
    out = f"batch-out-{os.getpid()}"  # relative: to the client's directory, not a worker's
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "batch",
                        str(robot_arm_path), "--out", out, "--criterion", "bic", "--seed", "1",
                        "--quiet", "--scheduler", cluster["address"]],
                       capture_output=True, text=True, cwd=client_dir, timeout=300)
    assert r.returncode == 0, r.stderr
    model = client_dir / out / "robot_arm.json"
    assert json.loads(model.read_text())["terms"] and not (ROOT / out).exists()
    import csv

    row = next(csv.DictReader(open(client_dir / out / "summary.csv")))
    assert (client_dir / row["model"]).resolve() == model.resolve()
    again = subprocess.run([sys.executable, "-m", "spm_sysid.apps.main", "batch",
                            str(robot_arm_path), "--out", out, "--quiet"],
                           capture_output=True, text=True, cwd=client_dir, timeout=120)
    assert again.returncode == 2 and "holds an earlier batch" in again.stderr


def test_sigterm_ends_a_study_and_its_workers_and_resume_works(tmp_path):
    """SIGTERM left both pool workers orphaned for over a minute."""
    import psutil

    out = tmp_path / "term"
    study = subprocess.Popen([sys.executable, "-m", "spm_sysid.apps.main", *STUDY,
                              "--out", str(out), "--workers", "2", "--generations", "120"],
                             cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    partial = out / "runs.partial.jsonl"
    deadline = time.monotonic() + 120
    while (not partial.exists() or len(partial.read_text().splitlines()) < 2) \
            and time.monotonic() < deadline:
        time.sleep(0.05)
    children = psutil.Process(study.pid).children(recursive=True)
    assert len(children) >= 2
    study.send_signal(signal.SIGTERM)
    _, err = study.communicate(timeout=60)
    assert study.returncode == 130 and "continue with --resume" in err, err
    gone, alive = psutil.wait_procs(children, timeout=10)
    assert not alive, [p.pid for p in alive]
    done = len(partial.read_text().splitlines())
    resumed = spm(*STUDY, "--out", str(out), "--resume", "--generations", "120")
    assert resumed.returncode == 0, resumed.stderr
    assert f"resumed: {done} run(s) were already done" in resumed.stdout
