"""Certifying the spaces users search, beside a general MIQP solver (make bench-certify-scale).

For the robot arm, the dryer and the heat exchanger (the first half of each,
``../shared/data``; a record that is missing is skipped with a line), in the
84-candidate space (ny = nu = 3, degree 3, with the constant; AIC and BIC),
the 164-candidate space (ny = nu = 4, degree 3; BIC and AICc) and the
454-candidate space (ny = nu = 6, degree 3; BIC); ``--orders`` picks among them:

* **ours**: the GA (seed 1) as warm start, then the branch and bound, within
  ``--time-limit`` (``--large-time-limit`` for 454) seconds, the warm start
  included, as ``spm-sysid certify`` runs it: status, value, lower bound, gap
  (in the criterion's units, as a share of the value, and as one-step MSE: the
  best structure's and the least any structure of at most its size may have),
  seconds and the process's peak memory; when not proved, what holds the bound
  (the reading of ``certify --explain`` over the 5 weakest open nodes);
* **SCIP** (pyscipopt, the ``bench`` extra; skipped with a line when it is not
  installed): best-subset least squares on the same scaled usable columns,
  formulated as Bertsimas, King and Mazumder (2016) do -- ``min ||y - X b||^2``
  with ``|b_j| <= M z_j``, ``sum z <= k``, z binary, M twice the largest
  least-squares coefficient of the full model -- for the sizes around the size
  of our best structure (k - 1, k, k + 1), each with the same time limit:
  status, its best value and its lower bound turned into the criterion's units,
  gap, seconds;
* **El0ps** (the ``bench`` extra, with the mpich wheel its MPI layer loads;
  84 candidates only, ``--skip-el0ps`` to leave it out): an exact branch and
  bound for least squares + lambda ||x||_0 + a ridge (:data:`EL0PS_RIDGE`) on
  unit-norm columns, lambda the criterion's price of one term at our SSE. It
  solves that regularised problem, not AIC/BIC (a log of the SSE) and not
  least squares without a ridge; its support is refitted without the ridge
  and valued by the criterion beside ours. A reference for speed at the same
  size. L0BnB 1.0.0 (2021) does not run on NumPy 2 (``np.Inf``).

Each run is its own process, so the peak memory is that run's. Figures, not
assertions; long: about 2 x 3 x 2 x (60 + 3 x 60) s + 3 x (600 + 3 x 600) s,
2.8 h, with the defaults (``--large-time-limit 120``: 56 min; ``--skip-scip
--skip-el0ps --orders 3``: 6 min), El0ps another 6 x 60 s or more.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import numpy as np

__all__ = ["main"]

RECORDS = (("robot arm", "robot_arm.dat"), ("dryer", "dryer.dat"),
           ("heat exchanger", "exchanger.dat"))


def _record(file: str):
    """The first half of a record beside the robot-arm data, or None."""
    from spm_sysid.core.io.data import load_io

    from .accuracy import _shared

    path = _shared(file)
    if path is None:
        return None
    u, y = load_io(path)
    h = len(y) // 2
    return u[:h], y[:h]


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _space(case: dict):
    """The case's term space: ny = nu = order, its degree, the constant at order 3."""
    from spm_sysid.core.model.terms import TermSpace

    return TermSpace(ny=case["order"], nu=case["order"], degree=case["degree"],
                     constant=case["order"] == 3)


def _problem(case: dict):
    """The case's regression problem on the first half of its record."""
    from spm_sysid.core.fit.problem import Problem

    return Problem.from_signals(*_record(case["file"]), _space(case))


def _ours(case: dict) -> dict:
    """The GA, then the branch and bound (one process)."""
    from spm_sysid.core.identify import identify
    from spm_sysid.core.search.certify import ensure_compiled
    from spm_sysid.core.search.explain import explain_table
    from spm_sysid.core.search.split import certify_data

    u, y = _record(case["file"])
    space = _space(case)
    ensure_compiled()
    started = time.perf_counter()
    limit = case["time_limit"]
    res = identify(u=u, y=y, term_space=space, criterion=case["criterion"], seed=1,
                   callback=lambda s: time.perf_counter() - started < 0.5 * limit,
                   auto_certify_time_limit=0, polish=True, selection="criterion",
                   operating_point="none")
    cert = certify_data(u, y, term_space=space, criterion=case["criterion"],
                        warm_start=res.model.mask, time_limit=limit, started=started,
                        node_limit=case.get("node_limit"), explain=5)
    rows = len(y) - space.max_lag
    return {"status": cert.status, "reason": cert.reason, "value": cert.value,
            "bound": cert.lower_bound,
            "gap": cert.gap, "terms": int(cert.mask.sum()), "nodes": cert.nodes,
            "seconds": time.perf_counter() - started, "rows": rows,
            "candidates": space.n_terms, "peak_mb": _peak_mb(), "mse": cert.one_step_mse,
            "mse_low": cert.mse_lower_bound,
            "reading": explain_table(cert.to_dict().get("weakest", []), cert.value)
            .splitlines()[-1] if cert.weakest else None, "mask": [
                int(i) for i in np.flatnonzero(cert.mask)]}


def _scip(case: dict) -> dict:
    """Best-subset least squares of size ``case['k']`` by SCIP (one process)."""
    import pyscipopt

    from spm_sysid.core.fit.criteria import get_criterion

    problem = _problem(case)
    X = problem.columns[:, problem.column_index(np.flatnonzero(problem.usable))]
    t = problem.target
    n, m = X.shape
    full = np.linalg.lstsq(X, t, rcond=None)[0]
    big_m = 2.0 * float(np.max(np.abs(full)))
    G, c, yy = X.T @ X, X.T @ t, float(t @ t)
    model = pyscipopt.Model()
    model.hideOutput()
    model.setParam("limits/time", float(case["time_limit"]))
    b = [model.addVar(lb=-big_m, ub=big_m, name=f"b{j}") for j in range(m)]
    z = [model.addVar(vtype="B", name=f"z{j}") for j in range(m)]
    for j in range(m):
        model.addCons(b[j] <= big_m * z[j])
        model.addCons(b[j] >= -big_m * z[j])
    model.addCons(pyscipopt.quicksum(z) <= case["k"])
    rss = model.addVar(lb=0.0, ub=None, name="rss")
    quad = pyscipopt.quicksum(G[i, j] * b[i] * b[j] for i in range(m) for j in range(m)
                              if G[i, j] != 0.0)
    model.addCons(rss >= quad - 2.0 * pyscipopt.quicksum(c[j] * b[j] for j in range(m)) + yy)
    model.setObjective(rss, "minimize")
    t0 = time.perf_counter()
    model.optimize()
    seconds = time.perf_counter() - t0
    crit = get_criterion(case["criterion"])
    rows = problem.rows

    def value(sse_scaled: float) -> float | None:
        if not np.isfinite(sse_scaled) or sse_scaled <= 0:
            return None
        sse = sse_scaled * problem.sse_scale
        return float(crit(np.array([sse]), rows, np.array([case["k"]]), None)[0])

    best = model.getObjVal() if model.getNSols() else float("inf")
    return {"status": model.getStatus(), "k": case["k"], "value": value(best),
            "bound": value(model.getDualbound()), "seconds": seconds, "peak_mb": _peak_mb(),
            "rss": best * problem.sse_scale if np.isfinite(best) else None}


#: The ridge of the El0ps run, on unit-norm columns and target. Smaller ridges leave its
#: root relaxation weak: at 1e-8 (robot arm, (3, 3, 3), BIC) one node took 180 s, three
#: times its time limit, and returned the empty model.
EL0PS_RIDGE = 1e-4


def _el0ps(case: dict) -> dict:
    """El0ps's branch and bound on the same columns: least squares + lambda ||x||_0 + ridge.

    Exact for that regularised problem, not for AIC/BIC: lambda is the criterion's
    price of one term at our structure's SSE (0.5 SSE units: SSE / n for AIC and
    AICc's leading term, SSE ln(n) / (2 n) for BIC), columns and target scaled
    to unit norm, ridge :data:`EL0PS_RIDGE`. Its support is refitted without the
    ridge and valued by the criterion, beside ours.
    """
    from el0ps.datafit import Leastsquares
    from el0ps.penalty import L2norm
    from el0ps.solver import BnbSolver

    from spm_sysid.core.fit.criteria import get_criterion

    problem = _problem(case)
    usable = np.flatnonzero(problem.usable)
    X, t = problem.columns[:, problem.column_index(usable)], problem.target
    A = np.asfortranarray(X / np.linalg.norm(X, axis=0))
    target = t / np.linalg.norm(t)
    rows = len(target)

    def sse_of(support: np.ndarray) -> float:
        coef = np.linalg.lstsq(A[:, support], target, rcond=None)[0]
        r = target - A[:, support] @ coef
        return float(r @ r)

    ours = np.isin(usable, case["mask"])
    per_term = float(np.log(rows)) if case["criterion"] == "bic" else 2.0  # AIC(c): 2
    lam = 0.5 * sse_of(ours) / rows * per_term
    t0 = time.perf_counter()
    res = BnbSolver(time_limit=case["time_limit"], relative_gap=1e-6).solve(
        Leastsquares(target), L2norm(EL0PS_RIDGE), A, lam)
    seconds = time.perf_counter() - t0
    support = np.abs(np.asarray(res.x).ravel()) > 1e-12
    crit = get_criterion(case["criterion"])
    value = None
    if support.any():
        sse = sse_of(support) * float(t @ t) * problem.sse_scale
        value = float(crit(np.array([sse]), rows, np.array([support.sum()]), None)[0])
    return {"status": str(res.status.value), "nodes": int(res.iter_count), "seconds": seconds,
            "terms": int(support.sum()), "value": value, "peak_mb": _peak_mb()}


def _child(kind: str, case: dict, timeout: float) -> dict:
    p = subprocess.run([sys.executable, "-m", "benchmarks.certify_scale", "--one", kind,
                        json.dumps(case)], capture_output=True, text=True,
                       timeout=timeout)
    if p.returncode != 0:
        return {"error": (p.stderr.strip().splitlines() or ["failed"])[-1]}
    return json.loads(p.stdout.strip().splitlines()[-1])


def _have_el0ps(args) -> bool:
    if args.skip_el0ps:
        return False
    try:
        import el0ps.solver  # noqa: F401 - needs an MPI library (the mpich wheel)
    except (ImportError, RuntimeError) as exc:
        print(f"El0ps: not usable here ({str(exc).splitlines()[0]}; pip install -e "
              f"'.[bench]'); its rows are skipped")
        return False
    return True


def _print_el0ps(case: dict, ours: dict) -> None:
    """El0ps on the same space, beside ours (84 candidates only: a reference for speed)."""
    res = _child("el0ps", {**case, "mask": ours["mask"]}, case["time_limit"] * 4 + 300)
    if "error" in res:
        print(f"    El0ps: failed: {res['error']}")
        return
    value = "-" if res["value"] is None else f"{res['value']:.2f}"
    print(f"    El0ps (least squares + lambda ||x||_0 + ridge {EL0PS_RIDGE:g}; exact for that "
          f"problem, not for {case['criterion'].upper()}): {res['status']}, "
          f"{res['nodes']} nodes, {res['seconds']:.1f} s, peak {res['peak_mb']:.0f} MB; its "
          f"{res['terms']} terms refitted without the ridge: {value} (ours {ours['value']:.2f})")
    sys.stdout.flush()


def run(args) -> None:
    try:
        import pyscipopt  # noqa: F401
        have_scip = not args.skip_scip
    except ImportError:
        have_scip = False
        print("SCIP: pyscipopt is not installed (pip install -e '.[bench]'); its columns "
              "are skipped")
    have_el0ps = _have_el0ps(args)
    cases = []
    present = [(name, file) for name, file in RECORDS if _record(file) is not None]
    for name, file in RECORDS:
        if (name, file) not in present:
            print(f"{name}: {file} not found beside the robot-arm data; skipped")
    for order, criteria in ((3, ("aic", "bic")), (4, ("bic", "aicc")), (6, ("bic",))):
        if order not in args.orders:
            continue
        limit = args.large_time_limit if order == 6 else args.time_limit
        for name, file in present:
            for crit in criteria:
                cases.append((name, file, order, crit, limit))
    print("first halves; ours: GA warm start + branch and bound within the time limit "
          "(warm start included); SCIP: best-subset MIQP of the same scaled columns per size")
    for name, file, order, crit, limit in cases:
        case = {"file": file, "order": order, "degree": 3, "criterion": crit,
                "time_limit": limit}
        ours = _child("ours", case, limit * 3 + 300)
        if "error" in ours:
            print(f"{name}, ({order},{order},3), {crit.upper()}: ours failed: {ours['error']}")
            continue
        pct = 100.0 * ours["gap"] / abs(ours["value"]) if ours["value"] else float("nan")
        mse, low = ours.get("mse"), ours.get("mse_low")
        mse_text = (f"; one-step MSE {mse:.4g}, no structure of at most {ours['terms']} "
                    f"terms below {low:.4g} ({100.0 * (1.0 - low / mse):.1f} % lower)"
                    if mse and low is not None else "")
        print(f"{name}, ({order},{order},3), {ours['candidates']} candidates, {crit.upper()}: "
              f"ours {ours['status']}, value {ours['value']:.2f}, bound {ours['bound']:.2f}, "
              f"gap {ours['gap']:.2f} ({pct:.2f} % of the value){mse_text}; "
              f"{ours['terms']} terms, {ours['nodes']} nodes, "
              f"{ours['seconds']:.1f} s, peak {ours['peak_mb']:.0f} MB")
        if ours.get("reading"):
            print(f"    what holds the bound, {ours['reading']}")
        sys.stdout.flush()
        if have_el0ps and order == 3:
            _print_el0ps(case, ours)
        if not have_scip:
            continue
        k = ours["terms"]
        for size in (k - 1, k, k + 1):
            if size < 1:
                continue
            res = _child("scip", {**case, "k": size}, limit * 3 + 300)
            if "error" in res:
                print(f"    SCIP k={size}: failed: {res['error']}")
                continue
            v, b = res["value"], res["bound"]
            gap = (v - b) if v is not None and b is not None else float("inf")
            print(f"    SCIP k <= {size}: {res['status']}, value "
                  f"{'-' if v is None else f'{v:.2f}'}, bound "
                  f"{'-' if b is None else f'{b:.2f}'}, gap {gap:.2f}, "
                  f"{res['seconds']:.1f} s, peak {res['peak_mb']:.0f} MB")
            sys.stdout.flush()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--time-limit", type=float, default=60.0,
                   help="seconds per 84- and 164-candidate run (ours, and SCIP per size)")
    p.add_argument("--orders", type=lambda s: {int(x) for x in s.split(",")},
                   default={3, 4, 6}, help="the spaces (ny = nu, degree 3): a comma list of "
                   "3 (84 candidates), 4 (164), 6 (454); default all")
    p.add_argument("--large-time-limit", type=float, default=600.0,
                   help="seconds per 454-candidate run")
    p.add_argument("--skip-scip", action="store_true", help="no SCIP runs")
    p.add_argument("--skip-el0ps", action="store_true", help="no El0ps runs")
    p.add_argument("--one", nargs=2, metavar=("KIND", "CASE"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.one:
        kind, case = args.one
        out = {"ours": _ours, "scip": _scip, "el0ps": _el0ps}[kind](json.loads(case))
        print(json.dumps(out))
        return 0
    run(args)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
