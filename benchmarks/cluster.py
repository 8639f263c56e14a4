"""Benchmark: the paper's 180-run study on this machine's pool and on a 2-worker Dask cluster.

``python -m benchmarks.cluster`` (``make bench-dask``) runs the study
(the paper's grid: AIC, BIC, PMIC2 x populations 200, 100 x SPM 0, 0.15 x 15
runs; no certification, so only the runs are timed) first on the local process
pool (one process per core), then on a Dask ``LocalCluster`` of two worker
processes with one thread each, and prints seconds, seconds per run, the
cluster's overhead per run and whether the records are identical.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """Run both and print the table."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=15, help="runs per setting (default 15)")
    args = p.parse_args(argv)
    from distributed import LocalCluster

    from spm_sysid.core.io.datasets import load_robot_arm
    from spm_sysid.tools.experiment import ExperimentConfig, run_experiment

    u, y = load_robot_arm()
    config = ExperimentConfig(runs=args.runs, certify_reference=False)
    n = len(config.criteria) * len(config.populations) * len(config.spm_fractions) * args.runs
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        local = run_experiment(u, y, config, out=f"{tmp}/local")
        t_local = time.perf_counter() - t0
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                          dashboard_address=None) as cluster:
            t1 = time.perf_counter()
            dask = run_experiment(u, y, config, out=f"{tmp}/dask",
                                  scheduler=cluster.scheduler_address)
            t_dask = time.perf_counter() - t1
    same = [(r.terms, r.final_value, r.best_curve) for r in local] == \
        [(r.terms, r.final_value, r.best_curve) for r in dask]
    print(f"study: {n} runs (the paper's grid, {args.runs} runs per setting), robot-arm data")
    print(f"{'runner':<28}{'seconds':>9}{'s/run':>8}{'failed':>8}")
    print(f"{'local pool (2 processes)':<28}{t_local:>9.1f}{t_local / n:>8.3f}"
          f"{len(local.failures):>8}")
    print(f"{'Dask LocalCluster (2 x 1)':<28}{t_dask:>9.1f}{t_dask / n:>8.3f}"
          f"{len(dask.failures):>8}")
    print(f"cluster overhead per run: {(t_dask - t_local) / n * 1e3:+.1f} ms "
          f"(ratio {t_dask / t_local:.2f}); identical records: {same}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
