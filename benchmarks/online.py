"""Benchmark of the online monitor and tracker (``make bench-online``).

1. Detection: a synthetic NARX system (``test/test_online.py``'s) identified on
   its first 2 000 samples, then streamed with a change at a known sample (a
   coefficient changed by 20 %, or a new term): how long until ``INVALID``
   at 100 Hz, over ``--seeds`` seeds; whether the identification on the data
   since the estimated change finds the new structure.
2. False alarms: 10^5 samples of the unchanged system: ``INVALID`` count.
3. Tracking: a coefficient drifting linearly by 30 % over 10^4 samples: the
   largest error in standard errors after the first 500 samples.
4. Cost: microseconds per sample of prediction + monitor + tracker (median
   of ``--repeats`` passes), against the cost of one-step prediction alone.

Prints figures; asserts nothing. No ROS (the node's ingest with monitoring on
is ``make bench-node``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np

__all__ = ["main"]

RATE = 100.0


def system(n, seed, change_at=None, kind="coefficient", noise=0.1):
    """y(t) = 0.5y(t-1) - 0.3y(t-2) + b u(t-1) + 0.3u(t-2) + 0.2y(t-1)u(t-1) + e.

    From ``change_at`` on: b = 1.0 -> 1.2 (``coefficient``), or a new term
    0.4 u(t-1)^2 (``term``). The tests use it too.
    """
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, n)
    e = noise * rng.standard_normal(n)
    y = np.zeros(n)
    for t in range(2, n):
        changed = change_at is not None and t >= change_at
        b = 1.2 if changed and kind == "coefficient" else 1.0
        y[t] = (0.5 * y[t - 1] - 0.3 * y[t - 2] + b * u[t - 1] + 0.3 * u[t - 2]
                + 0.2 * y[t - 1] * u[t - 1] + e[t])
        if changed and kind == "term":
            y[t] += 0.4 * u[t - 1] ** 2
    return u, y


def _session(model, residuals, tracking=False):
    from spm_sysid.core.online.session import OnlineSession

    return OnlineSession(model, residuals, tracking=tracking, sample_period=1 / RATE)


def run(args) -> None:
    from spm_sysid import identify
    from spm_sysid.core.model.terms import TermSpace

    space = TermSpace(ny=2, nu=2, degree=2)
    u0, y0 = system(2000, seed=1)
    model = identify(u=u0, y=y0, term_space=space, criterion="bic", seed=0).model
    residuals = model.residuals(u0, y0)
    print(f"model on 2000 samples: {model.equation()}")

    # 1. detection
    change = 1000
    for kind in ("coefficient", "term"):
        delays, found = [], 0
        for seed in range(args.seeds):
            u, y = system(change + 1000, seed=100 + seed, change_at=change, kind=kind)
            s = _session(model, residuals)
            first = est = None
            for t in range(len(y)):
                out = s.feed(int(t * 1e9 / RATE), u[t], y[t])
                if out is not None and out.state.state == "INVALID" and first is None:
                    first, est = t, s.change_stamp()
            if first is None:
                delays.append(float("inf"))
                continue
            delays.append((first - change) / RATE)
            since = int(round(est * RATE / 1e9))
            new = identify(u=u[since:], y=y[since:], term_space=space, criterion="bic",
                           seed=0).model
            found += ("u(t-1)^2" in new.terms) if kind == "term" else abs(
                new.coefficients[new.terms.index("u(t-1)")] - 1.2) < 0.05
        what = "new term found" if kind == "term" else "u(t-1) coefficient 1.2 +- 0.05"
        print(f"detection of a {kind} change at 100 Hz ({args.seeds} seeds): INVALID after "
              f"median {statistics.median(delays):.2f} s, max {max(delays):.2f} s; "
              f"re-identified ({what}) in {found} of {args.seeds}")

    # 2. false alarms
    u, y = system(args.samples, seed=7)
    s = _session(model, residuals)
    invalid = degraded = 0
    for t in range(len(y)):
        out = s.feed(int(t * 1e9 / RATE), u[t], y[t])
        if out is not None:
            if out.changed and out.state.state == "INVALID":
                invalid += 1
                s.monitor.reset()  # count every alarm, not only the first
            degraded += out.state.state == "DEGRADED"
    print(f"unchanged system, {args.samples} samples: {invalid} false INVALID, DEGRADED in "
          f"{degraded / len(y):.2%} of the samples")

    # 3. tracking a drift
    n = 12_000
    rng = np.random.default_rng(5)
    u = rng.uniform(-1, 1, n)
    b = 1.0 + 0.3 * np.arange(n) / 10_000
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 0.5 * y[t - 1] - 0.3 * y[t - 2] + b[t] * u[t - 1] + 0.05 * rng.standard_normal()
    lin = TermSpace(ny=2, nu=1, degree=1)
    m = identify(u=u[:2000], y=y[:2000], term_space=lin, criterion="bic", seed=0).model
    k = m.terms.index("u(t-1)")
    for forgetting in (0.99, 0.995):
        from spm_sysid.core.online.session import OnlineSession

        s = OnlineSession(m, m.residuals(u[:2000], y[:2000]), tracking=True,
                          forgetting=forgetting, sample_period=1 / RATE)
        worst = 0.0
        for t in range(2000, n):
            s.feed(int(t * 1e9 / RATE), u[t], y[t])
            if t >= 2500:
                worst = max(worst, abs(s.tracker.theta[k] - b[t]) / s.tracker.standard_errors[k])
        print(f"tracking a 30 % drift over 10^4 samples, forgetting {forgetting}: largest "
              f"error after the first 500 samples {worst:.2f} standard errors")

    # 4. cost per sample
    u, y = system(5000, seed=9)
    costs = {}
    for label, tracking in (("prediction + monitor", False),
                            ("prediction + monitor + tracker", True)):
        runs = []
        for _ in range(args.repeats):
            s = _session(model, residuals, tracking)
            t0 = time.perf_counter()
            for t in range(len(y)):
                s.feed(int(t * 1e9 / RATE), u[t], y[t])
            runs.append((time.perf_counter() - t0) / len(y) * 1e6)
        costs[label] = statistics.median(runs)
    from spm_sysid.core.online.predictor import OnlinePredictor

    runs = []
    for _ in range(args.repeats):
        p = OnlinePredictor(model)
        t0 = time.perf_counter()
        for t in range(len(y)):
            p.step(u[t], y[t])
        runs.append((time.perf_counter() - t0) / len(y) * 1e6)
    base = statistics.median(runs)
    print(f"cost per sample (median of {args.repeats} passes of 5000): prediction alone "
          f"{base:.1f} us; " + "; ".join(f"{k} {v:.1f} us ({v / base:.1f}x)"
                                         for k, v in costs.items()))


def main(argv: list[str] | None = None) -> int:
    """Command-line entry."""
    p = argparse.ArgumentParser(description="benchmark the online monitor and tracker")
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--samples", type=int, default=100_000)
    p.add_argument("--repeats", type=int, default=5)
    run(p.parse_args(argv))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
