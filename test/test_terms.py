import numpy as np
import pytest

from spm_sysid.core.model.terms import TermSpace


def test_paper_setting_has_44_terms_in_documented_order():
    ts = TermSpace()
    names = ts.term_names()
    assert ts.n_terms == len(names) == 44
    assert names[:8] == ["y(t-1)", "y(t-2)", "y(t-3)", "y(t-4)",
                         "u(t-1)", "u(t-2)", "u(t-3)", "u(t-4)"]
    assert names[8:12] == ["y(t-1)^2", "y(t-1)*y(t-2)", "y(t-1)*y(t-3)", "y(t-1)*y(t-4)"]
    assert names[12] == "y(t-1)*u(t-1)"
    assert names[-1] == "u(t-4)^2"
    assert len(set(names)) == 44
    assert sum("*" in n or "^" in n for n in names) == 36


def test_constant_delay_and_degree():
    ts = TermSpace(ny=2, nu=2, degree=3, delay=2, constant=True)
    names = ts.term_names()
    assert names[0] == "1"
    assert names[1:5] == ["y(t-1)", "y(t-2)", "u(t-2)", "u(t-3)"]
    assert "u(t-3)^3" in names and "y(t-1)^2*u(t-2)" in names
    # 1 + 4 + 10 + 20
    assert ts.n_terms == len(names) == 35
    assert ts.max_lag == 3


def test_regression_matrix_matches_hand_built_rows():
    rng = np.random.default_rng(3)
    u, y = rng.normal(size=30), rng.normal(size=30)
    ts = TermSpace()
    P = ts.regression_matrix(u, y)
    assert P.shape == (26, 44)
    names = ts.term_names()
    for row, t in ((0, 4), (7, 11), (25, 29)):
        lin = {f"y(t-{i})": y[t - i] for i in range(1, 5)}
        lin.update({f"u(t-{i})": u[t - i] for i in range(1, 5)})
        for j, name in enumerate(names):
            expected = 1.0
            for factor in name.split("*"):
                base, _, power = factor.partition("^")
                expected *= lin[base] ** int(power or 1)
            assert P[row, j] == pytest.approx(expected, rel=1e-14)
    assert np.array_equal(ts.target(y), y[4:])


@pytest.mark.parametrize("kwargs, message", [
    ({"degree": 0}, "degree"),
    ({"delay": -1}, "delay"),  # 0 is allowed since several inputs: feed-through
    ({"ny": -1}, "lags"),
    ({"ny": 0, "nu": 0}, "at least one"),
    ({"ny": 100, "nu": 100, "degree": 3}, "at most 100000"),
    ({"ny": 2.5}, "integer"),
])
def test_invalid_term_space(kwargs, message):
    with pytest.raises((ValueError, TypeError), match=message):
        TermSpace(**kwargs)


def test_dict_round_trip():
    ts = TermSpace(ny=3, nu=2, degree=3, delay=2, constant=True)
    assert TermSpace.from_dict(ts.to_dict()) == ts
