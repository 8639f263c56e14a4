"""An input that acts within the sample: the data check says so and names --delay."""

import re

import numpy as np
import pytest

from spm_sysid.core.fit.problem import Problem
from spm_sysid.core.io.data import load_io
from spm_sysid.core.model.terms import TermSpace
from spm_sysid.core.validate.excitation import check_problem
from spm_sysid.core.validate.feedthrough import ORDERS, within_sample

from .conftest import ROOT
from .test_cli import spm


def _plant(n: int = 4000, seed: int = 0, delay: int = 0):
    """y(t) = x(t) + 0.2x(t)^2 + noise, x(t) = 0.5x(t-1) + 0.5u(t-delay); u white."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(n)
    x = np.zeros(n)
    for t in range(delay, n):
        x[t] = 0.5 * x[t - 1] + 0.5 * u[t - delay]
    return u, x + 0.2 * x ** 2 + 0.01 * rng.standard_normal(n)


def _closed_loop(n: int = 4000, seed: int = 0):
    """y(t) = 0.9y(t-1) + 0.1u(t-1): a plant without feedthrough, and u(t) = r(t) - 2y(t).

    The reference is a multisine (a smooth set point, as the PD joint's): its next
    value follows from its last ones, so u(t) tells the noise in y(t).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n)
    r = np.sin(0.01 * t) + 0.5 * np.sin(0.037 * t) + 0.3 * np.sin(0.11 * t)
    u, y = np.zeros(n), np.zeros(n)
    for t in range(1, n):
        y[t] = 0.9 * y[t - 1] + 0.1 * u[t - 1] + 0.01 * rng.standard_normal()
        u[t] = r[t] - 2.0 * y[t]
    return u, y


def _warnings(u, y, delay: int = 1):
    space = TermSpace(ny=2, nu=2, degree=2, delay=delay)
    return check_problem(Problem.from_signals(u, y, space)).warnings


def test_the_share_is_what_least_squares_gives():
    """The share removed by u(t) beside the ARX of each order equals numpy's lstsq."""
    u, y = _plant()
    shares = []
    for n in ORDERS:
        rows = range(n, len(y))
        arx = np.array([[y[t - k] for k in range(1, n + 1)] + [1.0] +
                        [u[t - k] for k in range(1, n + 1)] for t in rows])
        target = y[n:]
        sse = [float(np.sum((target - X @ np.linalg.lstsq(X, target, rcond=None)[0]) ** 2))
               for X in (arx, np.column_stack([arx, u[n:]]))]
        shares.append(1 - sse[1] / sse[0])
    found = within_sample(y, u, [1], ["u"])
    assert found[0].input == "u" and found[0].lag == 0
    assert found[0].share == pytest.approx(min(shares), rel=1e-6)
    assert found[0].share > 0.9 and found[0].acts
    scaled = within_sample(y * 1e100, u * 1e-100, [1], ["u"])  # units do not matter
    assert scaled[0].share == pytest.approx(found[0].share, rel=1e-6)


def test_a_plant_acting_within_the_sample_is_said_with_the_delay_to_use(tmp_path):
    u, y = _plant()
    path = tmp_path / "take.csv"
    np.savetxt(path, np.column_stack([u, y]), delimiter=",", header="u,y", comments="")
    r = spm("check-data", "--data", str(path), "--inputs", "u", "--output", "y")
    assert r.returncode == 0, r.stderr
    line = next(w for w in r.stdout.splitlines() if "in the same step" in w)
    assert line.startswith("warning: y moves with u(t) in the same step")
    assert "identify with --delay 0" in line and "feedback controller" in line
    # propose-lags proposes lags from --delay on, and says the same
    lags = spm("propose-lags", "--data", str(path), "--inputs", "u", "--output", "y")
    assert lags.returncode == 0 and lags.stdout.splitlines()[-1] == line
    # with --delay 0 the space holds u(t): nothing earlier to test, nothing said
    r0 = spm("check-data", "--data", str(path), "--inputs", "u", "--output", "y",
             "--delay", "0")
    assert r0.returncode == 0 and "same step" not in r0.stdout
    # a model with u(t) describes the record: the held-out judgement agrees with the hint
    model = spm("identify", "--data", str(path), "--inputs", "u", "--output", "y",
                "--delay", "0", "--criterion", "bic", "--seed", "1")
    assert model.returncode == 0 and "u(t)" in model.stdout.splitlines()[2]


def test_a_delay_one_too_large_names_the_lag_before_it():
    u, y = _plant(delay=2)
    text = " ".join(_warnings(u, y, delay=3))
    assert "y moves with u(t-2) in the same step" in text and "--delay 2" in text
    assert not any("same step" in w for w in _warnings(u, y, delay=2))


def test_plants_that_act_a_sample_later_get_no_such_warning():
    u, y = _plant(delay=1)
    assert not any("same step" in w for w in _warnings(u, y))
    # the robot arm (the paper's record) and the dryer neither
    for name in ("robot_arm.dat", "dryer.dat"):
        path = ROOT.parent / "shared" / "data" / name
        if not path.exists():
            pytest.skip(f"{name} is not beside the repository")
        u, y = load_io(path)
        assert not any("same step" in w for w in _warnings(u, y))


def test_a_controller_that_reads_the_output_of_the_same_sample_is_named():
    """The test cannot tell a controller from feedthrough: the warning says both."""
    u, y = _closed_loop()
    line = next(w for w in _warnings(u, y) if "same step" in w)
    assert "computed from this y in the same sample" in line and "keep the delay" in line


def test_a_coupled_model_is_not_told_to_take_another_outputs_lag_0(tmp_path):
    """Two outputs of one state share its disturbance: y1(t) tells y0(t) almost exactly,
    but a coupled model reads the other outputs from lag 1 whatever --delay says (the
    warning named y1(t) and --delay 0 before); the input acts a sample later: no warning."""
    rng = np.random.default_rng(0)
    n = 3000
    u, w = rng.standard_normal(n), 0.1 * rng.standard_normal(n)
    x = np.zeros(n)
    for t in range(1, n):
        x[t] = 0.8 * x[t - 1] + 0.5 * u[t - 1] + w[t]
    y = np.column_stack([x, 2 * x]) + 0.005 * rng.standard_normal((n, 2))
    path = tmp_path / "two.csv"
    np.savetxt(path, np.column_stack([u, y]), delimiter=",", header="u,y0,y1", comments="")
    assert within_sample(y[:, 0], np.column_stack([u, y[:, 1]]), [1, 1],
                         ["u", "y1"])[1].acts  # what the test reads, were y1 an input
    r = spm("identify", "--data", str(path), "--inputs", "u", "--output", "y0,y1",
            "--ny", "1", "--nu", "1", "--degree", "1", "--criterion", "bic", "--seed", "1")
    assert r.returncode == 0, r.stderr
    line = next(x for x in r.stdout.splitlines() if x.startswith("y0(t) = "))
    gain = re.search(r"([0-9.]+)u\(t-1\)", line)  # beside y0(t-1) or y1(t-1): 0.5 either way
    assert gain and float(gain.group(1)) == pytest.approx(0.5, abs=0.02)
    assert "same step" not in r.stdout + r.stderr


def test_too_short_a_record_is_not_tested():
    """Fewer rows than 10 per column of the order-20 ARX: no statement (nor an error)."""
    u, y = _plant(n=400)
    assert within_sample(y, u, [1], ["u"]) == [] and within_sample(y[:9], u[:9], [1], ["u"]) == []
    assert within_sample(*_plant(n=600)[::-1], [1], ["u"])[0].acts
