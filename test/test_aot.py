"""The ahead-of-time build of the kernels: the same numbers as numba's JIT,
only for the sources it was built from, only for the argument types it holds."""

import importlib
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from spm_sysid.core.compiled import aot
from spm_sysid.core.compiled import registry as registry
from spm_sysid.core.compiled.aot import build_forced, build_status, jit_only
from spm_sysid.core.compiled.registry import Kernel, kernels
from spm_sysid.core.fit.problem import Problem
from spm_sysid.core.model.simulation import _run
from spm_sysid.core.search.certify import certify

from .conftest import ROOT


@pytest.fixture(scope="module")
def built():
    """The ahead-of-time build of these sources, made here when ``make setup`` did not.

    No test depends on what the set-up left behind; without a C compiler the
    tests that need the build skip, saying why.
    """
    status = build_status()
    if not status:
        from spm_sysid.core.jobs.warmup import compile_all

        _, status = compile_all()
        registry._loaded = None  # this process looked for a build before: look again
    if not status:
        pytest.skip(f"no ahead-of-time build: {status.reason}")
    return status


@pytest.mark.slow
def test_the_build_exports_the_kernels_commands_call(built):
    status = built
    table = json.loads(status.path.with_name(status.path.name.split(".")[0] + ".json")
                       .read_text())
    # the entry points the commands call are in it
    assert {"kernels.fit_structures", "branch_bound.expand", "simulation._run",
            "levenberg._refine_entry", "free_run._stable", "coupled._coupled",
            "coupled._coupled_sens", "kernels.qr_structures"} <= set(
        table["exports"])


def test_every_module_that_defines_kernels_is_in_the_build_hash():
    for name in aot.KERNEL_MODULES:
        importlib.import_module(f"spm_sysid.core.{name}")
    assert kernels()
    assert {k.key.split(".")[0] for k in kernels()} <= {
        m.rsplit(".", 1)[-1] for m in aot.KERNEL_MODULES}


def _both(fn):
    """fn() on the build (as commands run) and on numba's JIT."""
    with jit_only():
        jit = fn()
    with build_forced():
        return fn(), jit


@pytest.mark.slow
def test_the_build_and_the_jit_fit_score_simulate_and_certify_the_same(robot_arm, built):
    u, y = robot_arm
    problem = Problem.from_signals(u, y)
    n_terms = problem.evaluator("bic").n_terms
    rng = np.random.default_rng(5)
    masks = rng.random((300, n_terms)) < 0.3

    def fits():
        return problem.evaluator("bic").evaluate(masks)

    built, jitted = _both(fits)
    assert np.array_equal(built, jitted, equal_nan=True)
    assert np.isfinite(built).sum() > 250

    mask = np.zeros(problem.evaluator("bic").n_terms, dtype=bool)
    mask[[0, 1, 2, 3, 7, 8, 9, 10]] = True
    model = problem.model(problem.expand(mask))
    built, jitted = _both(lambda: model.simulate(u, y[:4]))
    assert np.array_equal(built, jitted)

    ev = problem.evaluator("aic")
    built, jitted = _both(lambda: certify(None, None, "aic", evaluator=ev, threads=1,
                                          time_limit=600))
    assert built.status == jitted.status == "optimal"
    assert np.array_equal(built.mask, jitted.mask) and built.value == jitted.value


def test_a_call_the_build_does_not_hold_runs_on_the_jit_with_the_same_result(robot_arm,
                                                                            built):
    u, y = robot_arm
    problem = Problem.from_signals(u, y)
    mask = np.zeros(problem.evaluator("bic").n_terms, dtype=bool)
    mask[[0, 1, 2, 3, 7, 8, 9, 10]] = True
    model = problem.model(problem.expand(mask))
    cm = model.compiled
    wide = np.column_stack([y, y])
    strided = wide[:, 0]  # not contiguous: the build holds contiguous arrays only
    assert not strided.flags.c_contiguous
    u2 = np.ascontiguousarray(u.reshape(len(u), -1), dtype=float)
    theta = np.ascontiguousarray(model.coefficients, dtype=float)
    lag = cm.max_lag
    args = (cm.gather, cm.y_lags, cm.u_lags, cm.u_cols, theta, u2)
    tail = (len(y), lag, -1e9, 1e9)
    with build_forced():
        checks = aot.exports_for("simulation._run")
    assert checks and not any(ok((*args, strided, *tail, np.empty(len(y) - lag)))
                              for ok, _ in checks)
    assert any(ok((*args, np.ascontiguousarray(strided), *tail, np.empty(len(y) - lag)))
               for ok, _ in checks)
    out, expect = np.empty(len(y) - lag), np.empty(len(y) - lag)
    with build_forced():
        at = _run(*args, strided, *tail, out)
    at_py = _run.py_func(*args, np.ascontiguousarray(strided), *tail, expect)
    assert at == at_py
    assert np.array_equal(out, expect)


def test_a_build_for_other_sources_is_never_loaded(tmp_path, monkeypatch, built):
    monkeypatch.setenv("SPM_SYSID_AOT_DIR", str(tmp_path))
    monkeypatch.setattr(registry, "_loaded", None)
    with build_forced():
        assert not build_status() and aot.exports_for("kernels.fit_structures") == []
    # the real build, renamed as if made from other sources
    real = (built.path, built.path.with_name(built.path.name.split(".")[0] + ".json"))
    for f in real:
        shutil.copy(f, tmp_path / f.name.replace(aot.source_hash(), "0" * 16))
    monkeypatch.setattr(registry, "_loaded", None)
    with build_forced():
        assert not build_status() and aot.exports_for("kernels.fit_structures") == []
    monkeypatch.setattr(registry, "_loaded", None)


def test_the_kernels_are_numba_dispatchers_inside_compiled_code():
    from spm_sysid.core.compiled.kernels import cholesky_rows

    assert isinstance(cholesky_rows, Kernel)
    gram = np.array([[4.0, 2.0], [2.0, 3.0]])
    L = np.zeros((2, 2))
    piv = np.zeros(2)
    first = cholesky_rows.jit(gram, np.array([0, 1]), 0, 2, L, piv, 1e-12, False, 2)
    assert first == -1
    assert np.allclose(L @ L.T, gram)


def test_the_quick_command_does_not_import_numba(built):
    code = ("import sys, io, contextlib\n"
            "from spm_sysid.apps.main import main\n"
            "sys.argv = ['spm-sysid', 'identify', '--quiet']\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    main()\n"
            "print('NUMBA', 'numba' in sys.modules, 'llvmlite' in sys.modules)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "NUMBA False False" in r.stdout


def test_a_large_batch_fitted_on_two_threads_gives_the_same_numbers(monkeypatch):
    from spm_sysid.core.fit import evaluator as evaluator_module
    from spm_sysid.core.fit.evaluator import StructureEvaluator

    rng = np.random.default_rng(3)
    P = rng.standard_normal((300, 120))
    P[:, 7] = P[:, 3] + 1e-9 * rng.standard_normal(300)  # near rank: QR arbitration too
    target = P[:, :30] @ rng.standard_normal(30) + 0.1 * rng.standard_normal(300)
    masks = rng.random((160, 120)) < rng.uniform(0.05, 0.6, size=(160, 1))
    out = {}
    for label, work in (("one thread", np.inf), ("two threads", 0.0)):
        monkeypatch.setattr(evaluator_module, "PARALLEL_FIT_WORK", work)
        out[label] = StructureEvaluator(P, target, "aic").evaluate(masks)
    if evaluator_module._fit_pool() is None:
        pytest.skip("one core: batches are never split")
    assert np.array_equal(out["one thread"], out["two threads"], equal_nan=True)
    assert np.isfinite(out["one thread"]).sum() > 100


def test_the_work_split_counts_what_neighbours_share():
    # a sorted batch's kernel skips the prefix a structure shares with the one before:
    # the split into halves weighs k^3 less that (checked against the index lists)
    from spm_sysid.core.fit.evaluator import _shared_prefix

    rng = np.random.default_rng(8)
    masks = rng.random((200, 40)) < 0.7
    masks[:, :10] = rng.random((200, 1)) < 0.9  # long common runs, and some without
    masks = masks[np.lexsort(~masks.T[::-1])]
    expect = [0]
    for a, b in zip(masks[:-1], masks[1:]):
        ia, ib = np.flatnonzero(a), np.flatnonzero(b)
        n = 0
        while n < min(len(ia), len(ib)) and ia[n] == ib[n]:
            n += 1
        expect.append(n)
    got = _shared_prefix(masks)
    assert np.array_equal(got, expect) and max(expect) > 10


def test_a_long_running_process_can_prefer_the_jit_which_releases_the_gil(monkeypatch):
    # the node does (spm_sysid.ros.entry): its subscriptions keep recording while a
    # kernel runs; the build would hold the GIL for a whole certification round
    monkeypatch.setattr(registry, "_prefer_jit", False)
    with build_forced():
        before = aot.exports_for("kernels.fit_structures")
        assert aot.prefer_jit() is True
        assert aot.exports_for("kernels.fit_structures") == []
        monkeypatch.setattr(registry, "_prefer_jit", False)
        assert aot.exports_for("kernels.fit_structures") == before


def test_the_build_is_named_for_this_cpu(monkeypatch):
    # compiled for the host CPU: a copy of the environment on another CPU must not load it
    here = aot.source_hash()
    aot.source_hash.cache_clear()
    monkeypatch.setattr(registry, "_cpu_signature", lambda: "flags : sse2")
    try:
        assert aot.source_hash() != here
    finally:
        aot.source_hash.cache_clear()
        monkeypatch.undo()
    assert aot.source_hash() == here
