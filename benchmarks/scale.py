"""Benchmark: the command that chooses everything, at real sizes (make bench-scale).

Runs ``spm-sysid identify --focus simulation --orders auto`` -- as a user types
it, in its own process -- on

* the Wiener-Hammerstein estimation record (``../shared/data/wh_est.dat``) cut
  to 10 000, 30 000 and 100 000 samples;
* a synthetic 1 kHz joint recording of 10 minutes (600 000 samples): the
  PD-controlled joint with viscous and Coulomb friction of the test helpers
  (``test/helpers/joint.py``);
* the simulated two-link arm (``benchmarks/two_link.py``) with its two outputs,
  100 000 samples (``--inputs tau1,tau2 --output q1,q2``: one coupled model,
  each output searched in the space it proposes), scored on 20 000 samples of
  a second record (RMSE from sample 10, per output, radians);

and prints, per size, the wall seconds, the peak resident memory of that
process (``os.wait4``), the phases its progress lines named, the model's
free-run RMSE on records it was not fitted on (the Wiener-Hammerstein test
part in mV from its sample 50, the benchmark's convention; for the joint the
mean over :data:`JOINT_TESTS` other recordings of the same length, from their
sample 50, beside the linear ARX's: :func:`spm_sysid.core.validate.arx.choose_arx`
on the same record -- the free run of an integrating output is one drift per
recording, and one recording ranks models by chance), and the
slope of log(time) against log(samples) over the sizes (1: linear cost). ``--repeats``
runs each size several times and prints the median. Figures, not assertions:
the limits the project keeps are 60 s for Silverbox (65 062 samples), 120 s
for Wiener-Hammerstein (100 000) and 1.5 GB on a 2-core machine.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["main"]

ROOT = Path(__file__).resolve().parents[1]
SIZES = (10_000, 30_000, 100_000)
COMMAND = ("identify", "--focus", "simulation", "--orders", "auto")


def test_helper(name: str):
    """The tests' simulator module ``test/helpers/<name>.py`` (the tests are no package here)."""
    spec = importlib.util.spec_from_file_location(f"spm_sysid_test_{name}",
                                                  ROOT / "test" / "helpers" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def _joint(seconds: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Torque and position of the tests' simulated joint (``test/helpers/joint.py``)."""
    return test_helper("joint").joint_record(seconds, seed=seed)


def _run(data: Path, extra: tuple[str, ...]) -> tuple[float, float, int, list[str]]:
    """(seconds, peak MiB, exit status, phases seen) of one identify run (extra: its options)."""
    exe = str(Path(sys.executable).with_name("spm-sysid"))
    t0 = time.perf_counter()
    p = subprocess.Popen([exe, *COMMAND, "--data", str(data), *extra],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    phases = []
    for line in p.stderr:
        head = line.split(":")[0].split(",")[0]
        if head and (not phases or phases[-1] != head) and not line.startswith(" "):
            phases.append(head)
    _, status, usage = os.wait4(p.pid, 0)
    seconds = time.perf_counter() - t0
    return seconds, usage.ru_maxrss / 1024.0, os.waitstatus_to_exitcode(status), phases


#: Held-out samples that initialise a free run and are left out of its error (the
#: Wiener-Hammerstein benchmark's convention, used for the joint too).
SKIP = 50


def _wh_test(shared: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """The Wiener-Hammerstein test part (None when it is not there)."""
    from spm_sysid.core.io.data import load_io

    path = shared / "wh_val.dat"
    return load_io(path) if path.is_file() else None


#: Other recordings of the joint a model is scored on (seeds 1, 2, ...; the mean RMSE).
JOINT_TESTS = 3


def _arx_rmse(fit: tuple[np.ndarray, np.ndarray], held: list[tuple[np.ndarray, np.ndarray]]
              ) -> float:
    """The linear ARX yardstick's mean free-run RMSE on the ``held`` records, fitted on ``fit``."""
    from spm_sysid.core.validate.arx import choose_arx, rmse

    arx = choose_arx(*fit)
    return float(np.mean([rmse(y, arx.simulate(u, y), SKIP)[0] for u, y in held]))


def _held_out(path: Path, held, scale: float) -> float:
    """The written model's mean free-run RMSE on the ``held`` records times ``scale``.

    NaN when there is no model or no record.
    """
    from spm_sysid.core.model.mimo import read_model_document

    if not held or not path.is_file():
        return float("nan")
    model, _ = read_model_document(path)
    skip = max(SKIP - model.term_space.max_lag, 0)
    errors = []
    for u, y in held:
        yhat, _ = model.run(u, y)
        e = y[model.term_space.max_lag:] - yhat
        errors.append(float(np.sqrt(np.nanmean(e[skip:] ** 2))))
    return scale * float(np.mean(errors))


def _arm_row(tmp: str, n: int) -> tuple[str, Path, list[tuple[np.ndarray, np.ndarray]]]:
    """The two-link arm's record of ``n`` samples as a CSV, and its second record."""
    from .two_link import record

    u, y = record(n, seed=0)
    path = Path(tmp) / "arm.csv"
    np.savetxt(path, np.column_stack([u, y]), fmt="%.10g", delimiter=",",
               header="tau1,tau2,q1,q2", comments="")
    return f"two-link arm, two outputs, {n}", path, [record(20_000, seed=1)]


def _held_out_outputs(path: Path, held) -> str:
    """The written coupled model's free-run RMSE per output on ``held`` (from sample 10)."""
    from spm_sysid.core.model.mimo import read_model_document

    if not held or not path.is_file():
        return "nan"
    model, _ = read_model_document(path)
    u, y = held[0]
    sim, _ = model.simulate(u, y)
    e = (y[model.max_lag:] - sim)[max(10 - model.max_lag, 0):]
    return " / ".join(f"{v:.4g}" for v in np.sqrt(np.nanmean(e ** 2, axis=0)))


def run(args) -> None:
    from spm_sysid.core.io.data import load_io

    shared = ROOT.parent / "shared" / "data"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        records = []
        wh = shared / "wh_est.dat"
        if wh.is_file():
            u, y = load_io(wh)
            for n in args.sizes:
                path = Path(tmp) / f"wh_{n}.dat"
                np.savetxt(path, np.column_stack([u[:n], y[:n]]), fmt="%.10g")
                records.append((f"Wiener-Hammerstein, first {n}", n, path))
        else:
            print(f"{wh} not found: the Wiener-Hammerstein sizes are skipped")
        test = _wh_test(shared)
        held = {"wh": [test] if test is not None else []}
        if args.joint_seconds > 0:
            tau, q = _joint(args.joint_seconds)
            path = Path(tmp) / "joint.dat"
            np.savetxt(path, np.column_stack([tau, q]), fmt="%.10g")
            records.append((f"joint at 1 kHz, {args.joint_seconds:g} s", len(q), path))
            held["joint"] = [_joint(args.joint_seconds, seed=k)
                             for k in range(1, JOINT_TESTS + 1)]
            print(f"joint: the linear ARX's free-run RMSE on {JOINT_TESTS} other recordings "
                  f"(mean) {_arx_rmse((tau, q), held['joint']):.4g} rad")
        if args.arm_samples > 0:
            label, path, held["arm"] = _arm_row(tmp, args.arm_samples)
            records.append((label, args.arm_samples, path))
        print(f"spm-sysid {' '.join(COMMAND)} --data FILE (median of {args.repeats}); "
              "held-out: the model's free-run RMSE on a record it was not fitted on")
        print(f"{'record':<36} {'samples':>8} {'seconds':>9} {'peak MiB':>9}  status  "
              f"{'held-out':>12}  phases")
        for label, n, path in records:
            model = Path(tmp) / "model.json"
            arm = label.startswith("two-link")
            extra = ("--inputs", "tau1,tau2", "--output", "q1,q2") if arm else ()
            runs = [_run(path, ("--seed", str(seed), "--json", str(model), *extra))
                    for seed in range(args.repeats)]
            seconds = float(np.median([r[0] for r in runs]))
            peak = float(np.median([r[1] for r in runs]))
            status = max(r[2] for r in runs)
            kind = "joint" if label.startswith("joint") else "wh"
            if arm:
                error = f"{_held_out_outputs(model, held['arm'])} rad"
            else:
                unit = "mV" if kind == "wh" else "rad"
                error = (f"{_held_out(model, held.get(kind), 1e3 if kind == 'wh' else 1.0):>8.4g}"
                         f" {unit:<3}")
            print(f"{label:<36} {n:>8} {seconds:>9.1f} {peak:>9.0f}  {status:>6}  "
                  f"{error:>12}  {' > '.join(runs[0][3])}", flush=True)
            if not arm:  # the slopes are over one output's records
                rows.append((n, seconds, label))
            model.unlink(missing_ok=True)
    wh_rows = [(n, s) for n, s, label in rows if label.startswith("Wiener")]
    if len(wh_rows) >= 2:
        x, t = np.log([r[0] for r in wh_rows]), np.log([r[1] for r in wh_rows])
        slope = float(np.polyfit(x, t, 1)[0])
        print(f"slope of log(seconds) against log(samples), Wiener-Hammerstein sizes: "
              f"{slope:.2f} (1: cost linear in the samples)")
    if len(rows) >= 2:
        x, t = np.log([r[0] for r in rows]), np.log([r[1] for r in rows])
        print(f"slope over every size: {float(np.polyfit(x, t, 1)[0]):.2f}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=list(SIZES),
                   help="samples of the Wiener-Hammerstein record to run on")
    p.add_argument("--joint-seconds", type=float, default=600.0,
                   help="seconds of the synthetic 1 kHz joint recording (0: skip)")
    p.add_argument("--arm-samples", type=int, default=100_000,
                   help="samples of the two-output two-link arm record (0: skip)")
    p.add_argument("--repeats", type=int, default=1, help="runs per size (median)")
    run(p.parse_args(argv))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
