"""Benchmark: where the time of a command goes, and the speed targets.

``python -m benchmarks.speed`` (``make bench-speed``) prints

1. **the quick command**: ``spm-sysid identify --quiet`` on the robot-arm data,
   whole process, median of ``--repeats`` runs, against the same command on
   numba's JIT (``SPM_SYSID_AOT=0``: no ahead-of-time build) and the DEAP baseline
   (:mod:`benchmarks.deap_ga`, ``--baseline-repeats`` runs, interleaved in
   the same call) and their ratio; then where the time goes: imports by
   package (``python -X importtime``) and each phase of the job in-process;
2. **the GA** at the paper's settings in-process (median of repeats, a fresh
   evaluator each), without and with the polish;
3. **simulation focus**: the robot-arm data (paper's space, default settings)
   and the two-tank records (``ny = nu = 3``, degree 3, constant, BIC); and
   the refinement alone: the robot arm's free-run refinements (30 evaluations
   at most, as a fold's) as one compiled call each, against the same solver's
   code run in Python over the compiled residuals, and their ratio;
4. with ``--large``: a GA run of 454 candidates (``ny = nu = 6``, degree 3)
   on the robot-arm data with BIC and with AIC (SPM 0.15).

Times depend on the machine; ratios measured in the same call are the
comparable figures. Needs the ``bench`` extra for the baseline (``make
bench-speed`` installs it).
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import time

__all__ = ["import_breakdown", "main", "phase_breakdown"]

_CLI = [sys.executable, "-m", "spm_sysid.apps.main"]


def _wall(cmd: list[str], env: dict | None = None) -> float:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {r.stderr.strip()[-400:]}")
    return time.perf_counter() - t0


def quick_command(repeats: int, baseline_repeats: int
                  ) -> tuple[list[float], list[float], list[float]]:
    """Wall seconds of ``identify``, of it on numba's JIT, and of the baseline, interleaved.

    The JIT runs have ``SPM_SYSID_AOT=0`` (no ahead-of-time build).
    """
    ours, jit, base = [], [], []
    no_build = {**os.environ, "SPM_SYSID_AOT": "0"}
    _wall(_CLI + ["identify", "--quiet"])  # warm caches
    _wall(_CLI + ["identify", "--quiet"], no_build)
    for i in range(max(repeats, baseline_repeats)):
        if i < repeats:
            ours.append(_wall(_CLI + ["identify", "--quiet"]))
            jit.append(_wall(_CLI + ["identify", "--quiet"], no_build))
        if i < baseline_repeats:
            base.append(_wall([sys.executable, "-m", "benchmarks.deap_ga"]))
    return ours, jit, base


def import_breakdown(top: int = 8) -> list[tuple[str, float]]:
    """(package, cumulative import seconds) of ``identify``'s imports, largest first."""
    r = subprocess.run([sys.executable, "-X", "importtime", *_CLI[1:], "identify", "--quiet"],
                       capture_output=True, text=True)
    totals: dict[str, float] = {}
    for line in r.stderr.splitlines():
        m = re.match(r"import time:\s+(\d+) \|\s+(\d+) \|( *)(\S+)", line)
        if m and len(m.group(3)) == 1:  # top-level imports: their cumulative time
            pkg = m.group(4).split(".")[0]
            if pkg == "spm_sysid":
                pkg = ".".join(m.group(4).split(".")[:3])
            totals[pkg] = totals.get(pkg, 0.0) + int(m.group(2)) / 1e6
    return sorted(totals.items(), key=lambda kv: -kv[1])[:top]


def phase_breakdown() -> list[tuple[str, float]]:
    """Seconds of each phase of the default identification, in this (warm) process."""
    from spm_sysid.core.fit.problem import Problem
    from spm_sysid.core.identify import _polish
    from spm_sysid.core.record import DataSpec, load_record
    from spm_sysid.core.search.certify import certify
    from spm_sysid.core.search.ga import GAConfig, run_ga
    from spm_sysid.core.validate.excitation import check_problem
    from spm_sysid.core.validate.validation import validate_model

    out = []
    t = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal t
        now = time.perf_counter()
        out.append((name, now - t))
        t = now

    rec = load_record(DataSpec())
    lap("read the data")
    problem = Problem.from_signals(rec.u, rec.y)
    check_problem(problem)
    ev = problem.evaluator("aic")
    lap("build the problem, data check")
    res = run_ga(ev, GAConfig(), seed=None)
    lap("GA (300 generations)")
    _polish(problem, ev, res)
    lap("polish")
    certify(None, None, "aic", evaluator=ev, warm_start=res.best_mask, time_limit=10)
    lap("certification")
    model = problem.model(problem.expand(res.best_mask))
    validate_model(model, rec.u, rec.y)
    lap("fit, validation, bands")
    return out


def ga_times(repeats: int) -> tuple[list[float], list[float]]:
    """Seconds of the GA at paper settings (fresh evaluator each), and of GA + polish."""
    from spm_sysid.core.fit.problem import Problem
    from spm_sysid.core.identify import _polish
    from spm_sysid.core.record import DataSpec, load_record
    from spm_sysid.core.search.ga import GAConfig, run_ga

    rec = load_record(DataSpec())
    problem = Problem.from_signals(rec.u, rec.y)
    run_ga(problem.evaluator("aic"), GAConfig(generations=5), seed=0)  # kernels loaded
    ga, polished = [], []
    for seed in range(repeats):
        ev = problem.evaluator("aic")
        t0 = time.perf_counter()
        res = run_ga(ev, GAConfig(), seed=seed)
        ga.append(time.perf_counter() - t0)
        _polish(problem, ev, res)
        polished.append(time.perf_counter() - t0)
    return ga, polished


def simulation_times(repeats: int) -> list[tuple[str, float, int]]:
    """(case, median seconds, terms) of the default simulation-focused identification."""
    from spm_sysid.core.identify import identify
    from spm_sysid.core.model.terms import TermSpace
    from spm_sysid.core.record import DataSpec, load_record

    from .tanks import record

    rec = load_record(DataSpec())
    cases = [("robot arm, paper's space, BIC", rec.u, rec.y, TermSpace(), "bic"),
             ("two tanks, ny=nu=3 deg 3 constant, BIC", *record(1),
              TermSpace(ny=3, nu=3, degree=3, constant=True), "bic")]
    out = []
    for label, u, y, ts, crit in cases:
        times, terms = [], 0
        for _ in range(repeats):
            t0 = time.perf_counter()
            m = identify(u=u, y=y, term_space=ts, criterion=crit, seed=1,
                         focus="simulation").model
            times.append(time.perf_counter() - t0)
            terms = len(m.terms)
        out.append((label, statistics.median(times), terms))
    return out


def refinement_times(repeats: int, structures: int = 12) -> tuple[float, float, int]:
    """Median seconds of refining ``structures`` structures compiled and in Python; evaluations.

    Random structures of the (3, 3, 2) space holding every linear term, on the
    robot-arm data; both solvers take the same steps (a test checks it).
    """
    import numpy as np

    from spm_sysid.core.fit.free_run import FreeRun
    from spm_sysid.core.fit.levenberg import (
        evaluate_free_run,
        levenberg_marquardt,
        refine_free_run,
    )
    from spm_sysid.core.fit.problem import fit_structure
    from spm_sysid.core.model.terms import TermSpace
    from spm_sysid.core.record import DataSpec, load_record

    rec = load_record(DataSpec())
    ts = TermSpace(ny=3, nu=3, degree=2)
    rng = np.random.default_rng(0)
    runs = []
    while len(runs) < structures:
        mask = np.array([len(t) == 1 for t in ts.terms])
        mask[rng.choice(ts.n_terms, size=4, replace=False)] = True
        model = fit_structure(rec.u, rec.y, mask, ts)
        runs.append((FreeRun(model, rec.u, rec.y, None, guard=True), model.coefficients))

    def compiled() -> int:
        return sum(refine_free_run(run, theta, 30).nfev for run, theta in runs)

    def python() -> int:
        return sum(levenberg_marquardt(lambda t, r=run: evaluate_free_run(r, t)[:2], theta,
                                       30).nfev for run, theta in runs)

    compiled(), python()  # load the kernels
    times: dict = {compiled: [], python: []}
    for _ in range(repeats):
        for solve in (compiled, python):
            t0 = time.perf_counter()
            evaluations = solve()
            times[solve].append(time.perf_counter() - t0)
    return statistics.median(times[compiled]), statistics.median(times[python]), evaluations


def large_space() -> list[tuple[str, float, int, float]]:
    """(criterion, GA seconds, terms, value) for 454 candidates on the robot-arm data."""
    from spm_sysid.core.fit.problem import Problem
    from spm_sysid.core.model.terms import TermSpace
    from spm_sysid.core.record import DataSpec, load_record
    from spm_sysid.core.search.ga import GAConfig, run_ga

    rec = load_record(DataSpec())
    problem = Problem.from_signals(rec.u, rec.y, TermSpace(ny=6, nu=6, degree=3))
    out = []
    for crit in ("bic", "aic"):
        ev = problem.evaluator(crit)
        t0 = time.perf_counter()
        res = run_ga(ev, GAConfig(), seed=1)
        out.append((crit, time.perf_counter() - t0, int(res.best_mask.sum()),
                    float(res.best_score)))
    return out


def _med(values: list[float]) -> str:
    return (f"median {statistics.median(values):.3f} s (min {min(values):.3f}, max "
            f"{max(values):.3f}, n={len(values)})")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.speed",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--baseline-repeats", type=int, default=2)
    p.add_argument("--large", action="store_true",
                   help="also the 454-candidate GA runs (about 1.5 minutes)")
    a = p.parse_args(argv)
    print(f"speed benchmark ({os.cpu_count()} cores); repeats {a.repeats}, "
          f"baseline repeats {a.baseline_repeats}", flush=True)

    from spm_sysid.core.compiled.aot import build_status

    status = build_status()
    ours, jit, base = quick_command(a.repeats, a.baseline_repeats)
    print("\n1. spm-sysid identify --quiet (robot arm, paper settings, AIC, polish and "
          "certification), whole process")
    print(f"   kernels' ahead-of-time build: {status.path or status.reason}")
    print(f"   spm-sysid identify   {_med(ours)}")
    print(f"   the same on the JIT  {_med(jit)}  (SPM_SYSID_AOT=0: imports numba; ratio "
          f"{statistics.median(jit) / statistics.median(ours):.2f}x)")
    if base:
        print(f"   DEAP + lstsq GA      {_med(base)}")
        print(f"   ratio baseline / identify: "
              f"{statistics.median(base) / statistics.median(ours):.1f}x")
    print("   imports of identify (cumulative, by package):")
    for name, sec in import_breakdown():
        print(f"     {name:<34} {sec:6.3f} s")
    print("   phases in a warm process:")
    for name, sec in phase_breakdown():
        print(f"     {name:<34} {sec:6.3f} s")

    ga, polished = ga_times(a.repeats)
    print("\n2. GA at the paper's settings, in-process (AIC, robot arm)")
    print(f"   GA alone             {_med(ga)}")
    print(f"   GA + polish          {_med(polished)}")

    print("\n3. simulation focus, default settings (validated selection), in-process")
    for label, sec, k in simulation_times(max(1, min(a.repeats, 3))):
        print(f"   {label:<42} {sec:6.2f} s  ({k} terms)")
    one, plain, evaluations = refinement_times(a.repeats)
    print(f"   12 refinements of robot-arm structures ({evaluations} evaluations): one compiled "
          f"call each {one:.3f} s, the same solver in Python {plain:.3f} s "
          f"(ratio {plain / one:.2f}x)")

    if a.large:
        print("\n4. 454 candidates (ny=nu=6, degree 3), robot arm, SPM 0.15, seed 1: one GA run")
        for crit, sec, k, value in large_space():
            print(f"   {crit.upper():<4} {sec:7.1f} s  {k} terms  value {value:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
