"""Benchmark: a coupled two-output identification of a two-link arm (``make bench-mimo``).

The arm of :mod:`benchmarks.two_link` (two torques in, two joint angles
out, 2e-4 rad noise): 4 000 samples to identify, a second record of 4 000 to
simulate. Prints each output's equation, whether it has the cross terms the
physics puts there (the other joint's lags or torque), the coupled free-run
fit on the second record (``--focus simulation``: after the joint refinement
on the coupled free-run error), and the time of the two-output identification
against the two single-output ones (each angle from the torques only) in the
same run (median of ``--repeats``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

__all__ = ["main"]


def run(args) -> None:
    from spm_sysid.core.jobs import JobSettings, run_job
    from spm_sysid.core.model.terms import TermSpace
    from spm_sysid.core.record import Record

    from .two_link import record

    tau, q = record(args.samples, seed=0)
    tau2, q2 = record(args.samples, seed=1)
    space = TermSpace(ny=2, nu=2, degree=args.degree, inputs=("tau1", "tau2"), output="q")
    kw = {"criterion": args.criterion, "seed": 0, "focus": args.focus}
    mimo, single = [], []
    for rep in range(args.repeats + 1):  # the first loads the compiled kernels: not timed
        t0 = time.perf_counter()
        res = run_job(Record.from_samples(tau, q, source="two-link arm",
                                          input_names=space.inputs, output_names=("q1", "q2")),
                      JobSettings.from_values({"ny": 2, "nu": 2, "degree": args.degree,
                                               "validation": "none", **kw}))
        if rep:
            mimo.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        for i, name in enumerate(("q1", "q2")):  # each output alone, the same job
            run_job(Record.from_samples(tau, q[:, i], source="two-link arm",
                                        input_names=space.inputs, output_name=name),
                    JobSettings.from_values({"ny": 2, "nu": 2, "degree": args.degree,
                                             "validation": "none", **kw}))
        if rep:
            single.append(time.perf_counter() - t0)
    fits = res.model.fits(tau2, q2)
    print(f"two-link arm, {args.samples} samples, ny=nu=2, degree {args.degree}, "
          f"{args.criterion.upper()}, focus {args.focus}; candidates per output: "
          f"{res.model.models[0].term_space.n_terms}")
    for name, other, model in zip(("q1", "q2"), (("q2", "tau2"), ("q1", "tau1")),
                                  res.model.models):
        cross = [t for t in model.terms if any(o in t for o in other)]
        f = fits[name]
        free = ("DIVERGED" if f["diverged_at"] is not None
                else f"{f['free_run_fit_percent']:.1f} %")
        print(f"  {model.equation()}")
        print(f"    {len(model.terms)} terms, cross terms {len(cross)} ({', '.join(cross[:6])}"
              f"{' ...' if len(cross) > 6 else ''}); second record: one-step fit "
              f"{f['one_step_fit_percent']:.2f} %, coupled free-run fit {free}")
    refined = res.model.metadata.get("coupled_refinement")
    if refined:
        print(f"  joint refinement on the coupled free-run error: normalised SSE "
              f"{refined['before']:.4g} -> {refined['after']:.4g} ({refined['evaluations']} "
              f"runs, {'taken' if refined['taken'] else 'not taken'})")
    print(f"time: two-output identification median {statistics.median(mimo):.2f} s (the "
          f"outputs on parallel threads); the two single-output ones one after the other "
          f"{statistics.median(single):.2f} s; ratio "
          f"{statistics.median(mimo) / statistics.median(single):.2f} ({args.repeats} runs)")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(description="benchmark a two-output (MIMO) identification")
    p.add_argument("--samples", type=int, default=4000)
    p.add_argument("--degree", type=int, default=2)
    p.add_argument("--criterion", default="bic")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--focus", default="prediction", choices=("prediction", "simulation"),
                   help="simulation: each output's own, then all refined jointly (coupled)")
    run(p.parse_args(argv))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
