"""Models on data they were not fitted on, against a linear ARX (make bench-accuracy).

For each record: estimate on the first half (a simulator: on its first
record), simulate the second half (its second record) in free run, and print
the second half's free-run RMSE and fit for

* the linear ARX model a user gets in one line (least squares, orders 1-10
  with a constant, the order chosen on the first half's own free run:
  :mod:`spm_sysid.core.validate.arx`);
* the default identification with the simulation focus (``--focus simulation
  --constant --criterion bic --seed 1``, the paper's space);
* the same with ``--orders auto`` (the lags and degree proposed from the first
  half, as ``propose-lags`` does).

Records: the robot arm, the dryer and the heat exchanger (``../shared/data``;
skipped with a line when missing), the two-tank simulator, and the two-link
arm with two outputs (coupled free run, against a linear MIMO ARX fitted the
same way; both focuses; ``--orders auto`` is for one output). Figures, not
assertions.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["main"]

#: Samples at the start of the held-out half left out of every error: the largest
#: ARX order tried (every model starts from measured samples there).
START = 10


def _shared(name: str) -> Path | None:
    from ..core.io.datasets import find_robot_arm

    try:
        here = find_robot_arm().parent
    except ValueError:
        here = Path(__file__).resolve().parents[2].parent / "shared" / "data"
    path = here / name
    return path if path.is_file() else None


def _records():
    """(name, (u1, y1), (u2, y2)) of every record that is here."""
    from ..core.io.data import load_io
    from . import tanks

    for name, file in (("robot arm", "robot_arm.dat"), ("dryer", "dryer.dat"),
                       ("heat exchanger", "exchanger.dat")):
        path = _shared(file)
        if path is None:
            print(f"{name}: {file} not found beside the robot-arm data; skipped")
            continue
        u, y = load_io(path)
        h = len(y) // 2
        yield name, (u[:h], y[:h]), (u[h:], y[h:])
    yield "two tanks (simulator)", tanks.record(1), tanks.record(2)


def _narx(u1, y1, settings: dict):
    from ..core.jobs import JobSettings, run_job
    from ..core.record import Record

    names = {}
    if np.ndim(y1) == 2:
        names = {"input_names": ("tau1", "tau2"), "output_names": ("q1", "q2")}
    record = Record.from_samples(u1, y1, source="first half", **names)
    t0 = time.perf_counter()
    result = run_job(record, JobSettings.from_values(settings))
    return result.model, time.perf_counter() - t0


def _narx_run(model, u2, y2) -> np.ndarray:
    """The model's free run of the held-out record, aligned with it (NaN before max_lag)."""
    if np.ndim(y2) == 2:  # coupled
        sim, _ = model.simulate(u2, y2)
        out = np.full(np.shape(y2), np.nan)
        out[model.max_lag:] = sim
        return out
    yhat, _ = model.run(u2, y2)
    out = np.full(len(y2), np.nan)
    out[model.term_space.max_lag:] = yhat
    return out


def _line(label: str, y2, sim, terms: str, seconds: float) -> str:
    from ..core.validate.arx import fit_percent, rmse

    r, f = rmse(y2, sim, START), fit_percent(y2, sim, START)
    rs = ", ".join("diverged" if not np.isfinite(v) else f"{v:.4g}" for v in r)
    fs = ", ".join("-" if not np.isfinite(v) else f"{v:.1f}" for v in f)
    return f"  {label:<40} RMSE {rs:<20} fit % {fs:<12} {terms:<12} {seconds:6.1f} s"


def run(args) -> None:
    from ..core.validate.arx import choose_arx
    from . import two_link

    base = {"focus": "simulation", "constant": True, "criterion": "bic", "seed": 1}
    print("second-half free-run RMSE (each record's units) and fit, estimated on the first "
          f"half; errors from sample {START} of the held-out part")
    for name, (u1, y1), (u2, y2) in _records():
        print(name)
        t0 = time.perf_counter()
        arx = choose_arx(u1, y1)
        print(_line(f"linear ARX (order {arx.order}, first half)", y2, arx.simulate(u2, y2),
                    f"{arx.theta.shape[0]} params", time.perf_counter() - t0))
        model, seconds = _narx(u1, y1, base)
        print(_line("default, --focus simulation", y2, _narx_run(model, u2, y2),
                    f"{len(model.terms)} terms", seconds))
        model, seconds = _narx(u1, y1, {**base, "orders": "auto"})
        o = model.metadata["orders"]
        print(_line(f"--orders auto (chose {o['ny']}, {o['nu']}, {o['degree']})", y2,
                    _narx_run(model, u2, y2), f"{len(model.terms)} terms", seconds))
        sys.stdout.flush()
    tau1, q1 = two_link.record(args.samples, seed=0)
    tau2, q2 = two_link.record(args.samples, seed=1)
    print(f"two-link arm, two outputs (record 1 -> record 2, {args.samples} samples, coupled "
          "free run; values per output q1, q2)")
    t0 = time.perf_counter()
    arx = choose_arx(tau1, q1)
    print(_line(f"linear MIMO ARX (order {arx.order})", q2, arx.simulate(tau2, q2),
                f"{arx.theta.size} params", time.perf_counter() - t0))
    for focus in ("prediction", "simulation"):
        settings = {**base, "focus": focus, "ny": 2, "nu": 2}
        model, seconds = _narx(tau1, q1, settings)
        terms = "+".join(str(len(m.terms)) for m in model.models) + " terms"
        print(_line(f"default, --focus {focus} (2, 2, 2)", q2, _narx_run(model, tau2, q2),
                    terms, seconds))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=4000, help="two-link arm record length")
    run(p.parse_args(argv))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
