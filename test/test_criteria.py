import math

import numpy as np
import pytest

from spm_sysid.core.fit.criteria import (
    CRITERIA,
    Criterion,
    get_criterion,
    make_pmic2,
    register_criterion,
)


def test_aic_and_bic_formulas():
    sse, n, k = np.array([2.5, 0.1]), 100, np.array([3, 7])
    assert np.allclose(CRITERIA["aic"](sse, n, k), n * np.log(sse / n) + 2 * k)
    assert np.allclose(CRITERIA["bic"](sse, n, k), n * np.log(sse / n) + k * math.log(n))


def test_pmic2_is_bic_plus_magnitude_penalty():
    sse, n, k = np.array([1.0, 1.0]), 50, np.array([2, 2])
    beta = np.array([[0.5, -2.0, 0.0], [0.5, 0.0, -0.001]])
    bic = CRITERIA["bic"](sse, n, k)
    assert np.allclose(make_pmic2(0.0)(sse, n, k, beta), bic)
    rho = 1.0
    expected = bic + math.log(n) * rho * np.array(
        [math.log1p(1 / 0.5) + math.log1p(1 / 2.0), math.log1p(1 / 0.5) + math.log1p(1 / 0.001)]
    )
    assert np.allclose(make_pmic2(rho)(sse, n, k, beta), expected)
    # the smaller coefficient costs more
    values = make_pmic2(rho)(sse, n, k, beta)
    assert values[1] > values[0]
    # a selected term with an exactly-zero coefficient is never preferred
    zero = np.array([[0.5, 0.0, 0.0]])
    assert make_pmic2(rho)(np.array([1.0]), n, np.array([2]), zero)[0] == np.inf
    with pytest.raises(ValueError):
        make_pmic2(-1)


def test_registry_and_user_callable():
    assert get_criterion("AIC") is CRITERIA["aic"]

    def my_crit(sse, n, k, coefficients):
        return sse + k

    crit = get_criterion(my_crit)
    assert crit.name == "my_crit" and crit.needs_coefficients
    assert np.allclose(crit(np.array([1.0, 2.0]), 10, np.array([1, 2]), np.zeros((2, 3))), [2, 4])
    with pytest.raises(ValueError, match="unknown criterion 'nope'"):
        get_criterion("nope")
    with pytest.raises(TypeError):
        get_criterion(3)
    register_criterion(Criterion("twice_aic", lambda s, n, k, b: 2 * (n * np.log(s / n) + 2 * k)))
    try:
        assert "twice_aic" in CRITERIA
    finally:
        CRITERIA.pop("twice_aic")
