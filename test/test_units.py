"""A record in other units gets the same answers (pascals and metres, not volts).

numpy's least squares cuts off singular values relative to the largest, so columns
of very different sizes lost the small ones: the friction check warned on a
second-order plant written with its input in units of 1e5 and its output in 1e-7,
and not on the same plant in volts; the linear ARX comparator chose order 10 there
and 9 in volts. The checks now fit scaled columns (spm_sysid.core.linalg).
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from spm_sysid.core.linalg import scaled_lstsq
from spm_sysid.core.validate.arx import choose_arx
from spm_sysid.core.validate.friction import strongest_friction_sign

sys.path.insert(0, str(Path(__file__).parent))
from helpers.signals import multisine, second_order, squared  # noqa: E402

EXE = str(Path(sys.executable).with_name("spm-sysid"))
UNITS = [(1.0, 1.0), (1e5, 1e-7), (1e-4, 1e6)]


def _plant(n: int = 5000, seed: int = 1):
    rng = np.random.default_rng(seed)
    u = multisine(n, rng, 0.05)
    return u, second_order(u, squared(0.1)) + 0.01 * rng.standard_normal(n)


def test_scaled_least_squares_keeps_a_small_column_numpy_would_cut():
    rng = np.random.default_rng(0)
    X = rng.standard_normal((200, 3)) * np.array([1e5, 1e-9, 0.0])
    target = X[:, 0] * 2.0 + X[:, 1] * 3e14  # both columns weigh alike in the target
    assert np.allclose(scaled_lstsq(X, target), [2.0, 3e14, 0.0], rtol=1e-9)
    numpy_answer = np.linalg.lstsq(X, target, rcond=None)[0]
    assert abs(numpy_answer[1]) < 1.0  # what the checks had: the small column cut


@pytest.mark.parametrize("su, sy", UNITS[1:])
def test_the_checks_and_the_linear_arx_answer_alike_in_any_units(su, sy):
    u, y = _plant()
    ref_sign = strongest_friction_sign(y, u)
    sign = strongest_friction_sign(y * sy, u * su)
    assert sign.share == pytest.approx(ref_sign.share, rel=1e-6, abs=1e-9)
    assert sign.p_value == pytest.approx(ref_sign.p_value, rel=1e-6) and sign.p_value > 0.01
    ref_arx, arx = choose_arx(u, y), choose_arx(u * su, y * sy)
    assert arx.order == ref_arx.order
    sim, ref = arx.simulate(u * su, y * sy) / sy, ref_arx.simulate(u, y)
    assert np.max(np.abs(sim - ref)) < 1e-6 * np.max(np.abs(ref))


def test_check_data_says_the_same_of_a_record_in_small_units(tmp_path):
    u, y = _plant()
    said = []
    for su, sy in UNITS[:2]:
        path = tmp_path / f"r{su:g}.csv"
        np.savetxt(path, np.column_stack([u * su, y * sy]), delimiter=",", header="u,y",
                   comments="")
        r = subprocess.run([EXE, "check-data", "--data", str(path), "--output", "y"],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        # which of two nearly dependent terms is named may differ by rounding
        said.append([line.split("(")[0] for line in r.stdout.splitlines()
                     if line.startswith("warning")])
    assert said[0] == said[1] and not any("friction" in w for w in said[1]), said
