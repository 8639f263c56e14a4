"""Benchmark: models on data they were not fitted on.

``python -m benchmarks.generalise`` (``make bench-generalise``) prints:

* **tanks**: the two-tank cascade (:mod:`benchmarks.tanks`), estimation
  record seed 1, test record seed 2 (another multisine phase draw); for every
  space ny = nu in {2, 3, 4} x degree {2, 3}, with a constant, BIC, the default
  simulation focus: terms, whether the test-record simulation diverged, its
  RMSE and fit, and the ratio of each RMSE to the best;
* **robot arm, first half -> second half**: the lag proposal's space on the
  first half, the default simulation focus; free-run fit on the second half
  (and, for reference, the paper's space and a linear space);
* **large space**: ``--ny 6 --nu 6 --degree 3`` with the default settings
  (prediction focus), first half -> second half: terms, warnings, one-step
  and free-run fit on the second half against the paper's space;
* **coverage**: 95 % intervals of a known NARX system over replicates.

Every identification uses seed 0. Figures, not assertions: the tests run short
versions of the same code.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

__all__ = ["coverage", "free_run_fit", "main", "tank_table"]


def free_run_fit(model, u: np.ndarray, y: np.ndarray) -> tuple[float, float, int | None]:
    """(RMSE, fit %, diverged_at) of the model's free run on (u, y)."""
    yhat, at = model.run(u, y, None)
    if at is not None:
        return float("inf"), float("-inf"), int(at)
    meas = model.measured(y)
    e = meas - yhat
    rmse = float(np.sqrt(np.mean(e * e)))
    fit = 100.0 * (1.0 - np.linalg.norm(e) / np.linalg.norm(meas - meas.mean()))
    return rmse, float(fit), None


def one_step_fit(model, u: np.ndarray, y: np.ndarray) -> float:
    meas = model.measured(y)
    e = model.residuals(u, y)
    return float(100.0 * (1.0 - np.linalg.norm(e) / np.linalg.norm(meas - meas.mean())))


def tank_table(orders=(2, 3, 4), degrees=(2, 3), seed: int = 0) -> list[dict]:
    """The tanks rows (see the module doc)."""
    from spm_sysid.core.identify import identify
    from spm_sysid.core.model.terms import TermSpace

    from .tanks import record

    u, y = record(1)
    ut, yt = record(2)
    rows = []
    for n in orders:
        for d in degrees:
            ts = TermSpace(ny=n, nu=n, degree=d, constant=True)
            t0 = time.perf_counter()
            m = identify(u=u, y=y, term_space=ts, criterion="bic", seed=seed,
                         focus="simulation").model
            seconds = time.perf_counter() - t0
            rmse, fit, at = free_run_fit(m, ut, yt)
            sel = m.metadata.get("selection", {})
            rows.append({"space": f"ny=nu={n} deg {d}", "candidates": ts.n_terms,
                         "terms": len(m.terms), "diverged_at": at, "rmse": rmse, "fit": fit,
                         "guard_removed": sel.get("removed_by_guard", 0),
                         "seconds": seconds})
    best = min(r["rmse"] for r in rows)
    for r in rows:
        r["ratio"] = r["rmse"] / best
    return rows


def coverage(replicates: int = 300, n: int = 300, seed: int = 2026) -> tuple[float, list]:
    """Share of 95 % intervals that hold the true coefficient (pooled, per coefficient)."""
    from spm_sysid.core.fit.problem import fit_structure
    from spm_sysid.core.model.terms import TermSpace

    truth = {"y(t-1)": 0.5, "y(t-2)": -0.3, "u(t-1)": 1.0, "u(t-1)*u(t-2)": 0.2}
    ts = TermSpace(ny=2, nu=2, degree=2)
    mask = np.array([name in truth for name in ts.term_names()])
    true = np.array([truth[name] for name in ts.term_names() if name in truth])
    rng = np.random.default_rng(seed)
    hits = np.zeros(len(true))
    for _ in range(replicates):
        u = rng.uniform(-1, 1, n)
        e = 0.1 * rng.standard_normal(n)
        y = np.zeros(n)
        for t in range(2, n):
            y[t] = (0.5 * y[t - 1] - 0.3 * y[t - 2] + u[t - 1] + 0.2 * u[t - 1] * u[t - 2]
                    + e[t])
        m = fit_structure(u, y, mask, ts)
        iv = m.uncertainty.intervals(m.coefficients)
        hits += (iv[:, 0] <= true) & (true <= iv[:, 1])
    return float(hits.sum() / (replicates * len(true))), list(hits / replicates)


def _halves():
    from spm_sysid.core.record import DataSpec, load_record

    rec = load_record(DataSpec())
    half = len(rec.y) // 2
    return rec.u[:half], rec.y[:half], rec.u[half:], rec.y[half:]


def robot_arm_holdout(seed: int = 0) -> list[tuple[str, int, float, float]]:
    """(what, terms, second-half free-run fit, seconds) for the holdout comparison."""
    from spm_sysid.core.identify import identify
    from spm_sysid.core.model.terms import TermSpace
    from spm_sysid.core.validate.orders import propose_orders

    u1, y1, u2, y2 = _halves()
    prop = propose_orders(u1, y1)
    out = []
    for label, ts in ((f"lag proposal ny=nu={prop.order} deg {prop.degree}",
                       TermSpace(ny=prop.order, nu=prop.order, degree=prop.degree)),
                      ("paper's space ny=nu=4 deg 2", TermSpace()),
                      (f"linear ny=nu={prop.order}", TermSpace(ny=prop.order, nu=prop.order,
                                                               degree=1))):
        t0 = time.perf_counter()
        m = identify(u=u1, y=y1, term_space=ts, seed=seed, focus="simulation").model
        out.append((label, len(m.terms), free_run_fit(m, u2, y2)[1],
                    time.perf_counter() - t0))
    return out


def large_space(seed: int = 0) -> list[tuple[str, int, float, float, int, float]]:
    """(what, terms, one-step fit, free-run fit, warnings, seconds), first -> second half."""
    from spm_sysid.core.identify import identify
    from spm_sysid.core.model.terms import TermSpace

    u1, y1, u2, y2 = _halves()
    out = []
    for label, ts in (("ny=nu=6 deg 3 (default settings)", TermSpace(ny=6, nu=6, degree=3)),
                      ("paper's space ny=nu=4 deg 2", TermSpace())):
        t0 = time.perf_counter()
        m = identify(u=u1, y=y1, term_space=ts, seed=seed).model
        out.append((label, len(m.terms), one_step_fit(m, u2, y2), free_run_fit(m, u2, y2)[1],
                    len(m.metadata.get("warnings") or []), time.perf_counter() - t0))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.generalise",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--skip-large", action="store_true",
                   help="leave out the ny=nu=6 degree-3 case (about 1-2 minutes)")
    a = p.parse_args(argv)
    print("generalisation benchmark: about 2-4 minutes (seed 0 everywhere)", flush=True)

    print("\ntwo-tank cascade: estimate on record 1, simulate record 2 "
          "(constant, BIC, focus simulation, defaults)")
    print(f"{'space':<16}{'cands':>6}{'terms':>6}{'diverged':>10}{'RMSE':>9}{'fit %':>8}"
          f"{'x best':>8}{'guard':>7}{'s':>7}")
    rows = tank_table()
    for r in rows:
        div = "no" if r["diverged_at"] is None else f"at {r['diverged_at']}"
        print(f"{r['space']:<16}{r['candidates']:>6}{r['terms']:>6}{div:>10}{r['rmse']:>9.4f}"
              f"{r['fit']:>8.1f}{r['ratio']:>8.2f}{r['guard_removed']:>7}{r['seconds']:>7.1f}")
    print(f"diverged: {sum(r['diverged_at'] is not None for r in rows)} of {len(rows)}; "
          f"worst RMSE / best: {max(r['ratio'] for r in rows):.2f}")

    print("\nrobot arm: estimate on the first half, simulate the second (focus simulation)")
    for label, k, fit, s in robot_arm_holdout():
        print(f"  {label:<32} {k:>3} terms  free-run fit {fit:6.1f} %  ({s:.1f} s)")

    if not a.skip_large:
        print("\nlarge space, default settings (prediction focus): first half -> second half")
        for label, k, one, free, w, s in large_space():
            print(f"  {label:<34} {k:>3} terms  one-step fit {one:6.2f} %  free-run fit "
                  f"{free:6.1f} %  {w} warning(s)  ({s:.1f} s)")

    pooled, per = coverage()
    print(f"\ncoverage of 95 % intervals, 300 replicates x 4 coefficients: {100 * pooled:.1f} %"
          f" (per coefficient: {', '.join(f'{100 * v:.1f}' for v in per)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
