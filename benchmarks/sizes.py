"""Benchmark: GA run time and peak memory against the term space's size and the samples.

``spm-sysid bench-sizes`` prints one table. Each cell runs in its own process
(so its peak resident memory is its own) with the paper's GA settings
(population 200, 300 generations, SPM 0.15; term-space rows also with SPM 0).
The compiled kernel is loaded once per process before timing (its seconds are
shown as ``load s``). A run that would exceed
``--budget`` seconds is stopped there and its time per run extrapolated from
the generations done (marked ``~``). Rows:

* term spaces on the robot-arm data: 44 (paper), 164 (degree 3), 454 (6 lags,
  degree 3), 968 (8 lags, degree 3), 2 299 (11 lags, degree 3);
* samples on the paper's space: 1 k, 10 k, 100 k samples of a synthetic NARX
  system (the robot-arm record has only 1 024).

With ``--fastcan`` (needs the benchmark-only dependency ``fastcan``), each
term-space row also gets the forward-selection baseline: FastCan selects k
terms for k = 1 .. 60 on the same regression matrix, the criterion of each
selection is computed by the reference least-squares fit, and the best value
is compared with the GA's.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time

import numpy as np

__all__ = ["add_options", "main", "run"]

SPACES = [(4, 4, 2), (4, 4, 3), (6, 6, 3), (8, 8, 3), (11, 11, 3)]
SAMPLES = [1_000, 10_000, 100_000]


def synthetic(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A NARX system in the paper's space (5 terms, one product), with noise."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, n)
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = (0.6 * y[t - 1] - 0.2 * y[t - 2] + 0.8 * u[t - 1] + 0.3 * u[t - 2]
                + 0.1 * y[t - 1] * u[t - 1])
    return u, y + 0.01 * rng.standard_normal(n)


def _cell(spec: dict) -> dict:
    """One measurement, in this (child) process."""
    from spm_sysid.core.fit.evaluator import StructureEvaluator
    from spm_sysid.core.identify import identify
    from spm_sysid.core.io.datasets import load_robot_arm
    from spm_sysid.core.model.terms import TermSpace
    from spm_sysid.core.search.ga import GAConfig

    ny, nu, degree = spec["space"]
    u, y = load_robot_arm() if spec["samples"] is None else synthetic(spec["samples"])
    space = TermSpace(ny=ny, nu=nu, degree=degree)
    t0 = time.perf_counter()  # once per process: load (or compile) the numba kernel
    StructureEvaluator(np.eye(3), np.ones(3)).evaluate(np.eye(3, dtype=bool))
    warmup = time.perf_counter() - t0

    def run_ga(spm: float) -> dict:
        budget, start = spec["budget"], time.perf_counter()
        done = {"gens": 0}

        def callback(stats):
            done["gens"] = stats.generation
            return time.perf_counter() - start < budget

        res = identify(u=u, y=y, term_space=space, criterion=spec["criterion"], seed=1,
                       ga=GAConfig(spm_fraction=spm), callback=callback,
                       operating_point="none")
        seconds = time.perf_counter() - start
        full = done["gens"] >= 300
        return {"seconds": seconds if full else seconds * 300 / max(done["gens"], 1),
                "extrapolated": not full, "generations": done["gens"],
                "value": res.ga.best_score, "model_terms": len(res.model.terms)}

    out = {"terms": space.n_terms, "samples": len(y), "warmup": warmup, **run_ga(0.15)}
    out["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if spec.get("spm0"):
        out["spm0"] = run_ga(0.0)
    if spec.get("fastcan"):
        out["fastcan"] = _fastcan(space, u, y, spec["criterion"])
    return out


def _fastcan(space, u, y, criterion) -> dict:
    from fastcan import FastCan

    from spm_sysid.core.fit.lstsq import reference_score

    P, target = space.regression(u, y)
    best, best_k, t0 = np.inf, 0, time.perf_counter()
    for k in range(1, min(60, space.n_terms) + 1):
        sel = FastCan(n_features_to_select=k, verbose=0).fit(P, target)
        mask = np.zeros(space.n_terms, dtype=bool)
        mask[sel.indices_] = True
        value = reference_score(P, target, mask, criterion)
        if value < best:
            best, best_k = value, k
    return {"value": best, "model_terms": best_k, "seconds": time.perf_counter() - t0}


def _secs(o: dict) -> str:
    return ("~" if o["extrapolated"] else "") + format(o["seconds"], ".2f")


def _value(o: dict) -> str:
    """The best criterion value; in parentheses when the run was stopped early."""
    return f"({o['value']:.2f})" if o["extrapolated"] else f"{o['value']:.2f}"


def add_options(p) -> None:
    """The command's options (``spm-sysid bench-sizes --help``)."""
    p.add_argument("--budget", type=float, default=60.0,
                   help="seconds per cell before extrapolating (default 60)")
    p.add_argument("--criterion", default="bic", choices=("aic", "bic"))
    p.add_argument("--fastcan", action="store_true", help="compare with FastCan")
    p.add_argument("--max-terms", type=int, default=2500, help="skip larger spaces")


def main(argv: list[str] | None = None) -> int:
    """Entry of each cell's process (``--cell JSON``) and of a direct run."""
    import argparse

    p = argparse.ArgumentParser(prog="spm-sysid bench-sizes")
    add_options(p)
    p.add_argument("--cell", help=argparse.SUPPRESS)  # internal: one cell, JSON
    args = p.parse_args(argv)
    if args.cell:
        print(json.dumps(_cell(json.loads(args.cell))))
        return 0
    return run(args)


def run(args) -> int:
    """Print the table."""
    print(f"GA run time and peak memory (population 200, 300 generations, SPM 0.15 and "
          f"SPM 0, {args.criterion.upper()}, one BLAS thread, budget {args.budget:g} s per "
          f"cell; s/run excludes loading the compiled kernel once per process, shown as "
          f"'load s')")
    print(f"{'data':<12} {'terms':>6} {'samples':>8} {'load s':>6} {'s/run':>9} {'peak MB':>8} "
          f"{'GA value':>11} {'k':>4} {'SPM0 s/run':>10} {'SPM0 value':>11} {'k':>4}"
          + ("   FastCan value    k      s" if args.fastcan else ""))
    cells = [{"space": s, "samples": None} for s in SPACES] + \
        [{"space": SPACES[0], "samples": n} for n in SAMPLES]
    for cell in cells:
        from spm_sysid.core.model.terms import TermSpace

        if TermSpace(ny=cell["space"][0], nu=cell["space"][1],
                     degree=cell["space"][2]).n_terms > args.max_terms:
            continue
        spec = dict(cell, budget=args.budget, criterion=args.criterion,
                    fastcan=args.fastcan and cell["samples"] is None,
                    spm0=cell["samples"] is None)
        r = subprocess.run([sys.executable, "-m", "benchmarks.sizes", "--cell",
                            json.dumps(spec)], capture_output=True, text=True,
                           env={**__import__("os").environ, "OPENBLAS_NUM_THREADS": "1"})
        if r.returncode != 0:
            print(f"cell {cell} failed: {r.stderr.strip().splitlines()[-1]}")
            continue
        o = json.loads(r.stdout)
        label = "robot arm" if cell["samples"] is None else "synthetic"
        line = (f"{label:<12} {o['terms']:>6} {o['samples']:>8} {o['warmup']:>6.2f} "
                f"{_secs(o):>9} {o['peak_mb']:>8.0f} {_value(o):>11} {o['model_terms']:>4}")
        z = o.get("spm0")
        line += (f" {_secs(z):>10} {_value(z):>11} {z['model_terms']:>4}" if z else
                 f" {'':>10} {'':>11} {'':>4}")
        if "fastcan" in o:
            f = o["fastcan"]
            line += f"   {f['value']:>13.2f} {f['model_terms']:>4} {f['seconds']:>6.1f}"
        print(line, flush=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
