"""Benchmark: certifying the optimum on the robot-arm data and on records made hard on purpose.

``python -m benchmarks.certify`` (``make bench-certify``) runs, for
each case and criterion, the GA (seed 1, the paper's settings) and then the
branch and bound warm-started with its result, within ``--time-limit`` seconds,
and prints one row each: status, the GA's value, the certified (or best found)
value, the lower bound's gap, nodes and seconds.

The hard cases are simulated here (no third-party data), each the kind of record
that makes the candidate columns nearly collinear and many structures nearly
equal, in the paper's 44-term space:

* ``ar-*``: a smooth input (AR(1) with coefficient 0.9-0.99), much noise;
* ``dryer-*``: a two-level input and an output far from zero, little noise (a
  heater in a tube, 1 000 samples);
* ``exchanger-*``: a slowly stepping input, a static nonlinearity and an output
  around 100 (a heat exchanger, 4 000 samples).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable

import numpy as np

__all__ = ["CASES", "main"]


def _ar(seed: int, n: int, smooth: float, noise: float) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    e = rng.standard_normal(n)
    u = np.zeros(n)
    for t in range(1, n):
        u[t] = smooth * u[t - 1] + e[t]
    u /= np.abs(u).max()
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = (1.2 * y[t - 1] - 0.5 * y[t - 2] + 0.4 * u[t - 1] + 0.1 * u[t - 2] * y[t - 1]
                + 0.05 * u[t - 1] ** 2)
    return u, y + noise * y.std() * rng.standard_normal(n)


def _dryer(seed: int, n: int = 1000, noise: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    u = np.empty(n)
    level = 3.41
    for t in range(n):
        if rng.random() < 0.12:
            level = 9.82 - level  # 3.41 <-> 6.41
        u[t] = level
    y = np.full(n, 4.0)
    for t in range(4, n):
        y[t] = (1.29 * y[t - 1] - 0.41 * y[t - 2] + 0.065 * u[t - 3] + 0.04 * u[t - 4]
                + 0.002 * y[t - 1] * u[t - 3] + 0.1)
    return u, y + noise * rng.standard_normal(n)


def _exchanger(seed: int, n: int = 4000, noise: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    u = np.empty(n)
    level = 0.5
    for t in range(n):
        if rng.random() < 0.03:
            level = rng.uniform(0.1, 0.9)
        u[t] = level + 0.02 * rng.standard_normal()
    x = np.zeros(n)
    for t in range(2, n):
        x[t] = 1.6 * x[t - 1] - 0.64 * x[t - 2] + 0.04 * (-2.0 * u[t - 1] + 1.5 * u[t - 1] ** 2)
    return u, 100.0 + 10.0 * x + noise * rng.standard_normal(n)


def _robot_arm() -> tuple[np.ndarray, np.ndarray]:
    from spm_sysid.core.io.datasets import load_robot_arm

    return load_robot_arm()


#: name -> function returning (u, y)
CASES: dict[str, Callable[[], tuple[np.ndarray, np.ndarray]]] = {
    "robot-arm": _robot_arm,
    "ar-0.90": lambda: _ar(0, 1000, 0.90, 0.05),
    "ar-0.97": lambda: _ar(1, 2000, 0.97, 0.2),
    "ar-0.99": lambda: _ar(2, 4000, 0.99, 0.5),
    "white-noisy": lambda: _ar(3, 1000, 0.0, 1.0),
    "dryer-0": lambda: _dryer(0),
    "dryer-1": lambda: _dryer(1),
    "exchanger-0": lambda: _exchanger(0),
    "exchanger-1": lambda: _exchanger(1),
}


def main(argv: list[str] | None = None) -> int:
    """Run the cases and print the table."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--time-limit", type=float, default=60.0,
                   help="seconds per certification (default 60)")
    p.add_argument("--cases", default=",".join(CASES),
                   help=f"comma list of cases (default all: {','.join(CASES)})")
    p.add_argument("--criteria", default="aic,bic", help="comma list (default aic,bic)")
    p.add_argument("--seeds", type=int, default=5,
                   help="GA runs per case and criterion for the reach table (0: skip it)")
    p.add_argument("--first-seed", type=int, default=1,
                   help="the reach table's seeds are first-seed .. first-seed + seeds - 1")
    args = p.parse_args(argv)
    from spm_sysid.core.identify import identify
    from spm_sysid.core.model.terms import TermSpace
    from spm_sysid.core.search.split import certify_data

    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        p.error(f"unknown case(s) {', '.join(unknown)}; known: {', '.join(CASES)}")
    criteria = [c.strip() for c in args.criteria.split(",") if c.strip()]
    ts = TermSpace()
    print(f"certification, {ts.n_terms} candidate terms, time limit {args.time_limit:g} s")
    print(f"{'case':<13}{'N':>6} {'crit':<5}{'status':<9}{'GA':>12}{'certified':>12}"
          f"{'gap':>8}{'nodes':>10}{'seconds':>9}")
    certified = total = 0
    for name in cases:
        u, y = CASES[name]()
        for crit in criteria:
            res = identify(u=u, y=y, term_space=ts, criterion=crit, seed=1, polish=False,
                           auto_certify_time_limit=0, selection="criterion",
                           operating_point="none")
            t0 = time.perf_counter()
            cert = certify_data(u, y, term_space=ts, criterion=crit,
                                warm_start=res.model.mask, time_limit=args.time_limit)
            seconds = time.perf_counter() - t0
            total += 1
            certified += cert.status == "optimal"
            print(f"{name:<13}{len(y):>6} {crit:<5}{cert.status:<9}{res.ga.best_score:>12.2f}"
                  f"{cert.value:>12.2f}{cert.gap:>8.2f}{cert.nodes:>10}{seconds:>9.2f}",
                  flush=True)
    print(f"certified {certified} of {total}; gap = best found - lower bound (0 when optimal)")
    if args.seeds:
        reach(cases, criteria, args.seeds, args.time_limit, args.first_seed)
    return 0


def reach(cases: list[str], criteria: list[str], seeds: int, time_limit: float,
          first_seed: int = 1) -> None:
    """How often the GA alone, and the GA with its polish, reach the certified optimum."""
    from spm_sysid.core.fit.problem import Problem
    from spm_sysid.core.identify import identify_problem
    from spm_sysid.core.model.terms import TermSpace
    from spm_sysid.core.options import SearchOptions
    from spm_sysid.core.search.certify import certify

    print(f"\nGA (paper settings) alone and with the polish, seeds {first_seed}.."
          f"{first_seed + seeds - 1}: runs that reach "
          "the certified optimum (within 1e-6)")
    print(f"{'case':<13} {'crit':<5}{'optimum':>12}{'GA':>6}{'GA+polish':>11}"
          f"{'worst miss':>12}{'polish s':>10}")
    totals = [0, 0, 0]
    for name in cases:
        u, y = CASES[name]()
        problem = Problem.from_signals(u, y, TermSpace())
        for crit in criteria:
            opt = certify(None, None, crit, evaluator=problem.evaluator(crit),
                          time_limit=time_limit)
            ga_hits = polish_hits = 0
            miss, polish_seconds = 0.0, []
            for seed in range(first_seed, first_seed + seeds):
                runs = {}
                for polish in (False, True):
                    t0 = time.perf_counter()
                    res = identify_problem(problem, SearchOptions(
                        criterion=crit, seed=seed, polish=polish, auto_certify_time_limit=0,
                        selection="criterion"), check_data=False)
                    runs[polish] = (res.model.criterion_value, time.perf_counter() - t0)
                ga_hits += runs[False][0] <= opt.value + 1e-6
                polish_hits += runs[True][0] <= opt.value + 1e-6
                miss = max(miss, runs[True][0] - opt.value)
                polish_seconds.append(runs[True][1] - runs[False][1])
            totals[0] += ga_hits
            totals[1] += polish_hits
            totals[2] += seeds
            mark = "" if opt.status == "optimal" else " (not proven)"
            print(f"{name:<13} {crit:<5}{opt.value:>12.2f}{ga_hits:>4}/{seeds}"
                  f"{polish_hits:>8}/{seeds}{miss:>12.3g}"
                  f"{float(np.median(polish_seconds)):>10.3f}{mark}", flush=True)
    print(f"reached: GA alone {totals[0]} of {totals[2]} ({100 * totals[0] / totals[2]:.0f} %), "
          f"GA + polish {totals[1]} of {totals[2]} ({100 * totals[1] / totals[2]:.0f} %)")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
