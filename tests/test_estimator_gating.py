"""The NIS gate against scipy.stats' chi-square quantile (the reference the estimators used before)."""
from __future__ import annotations

import pytest
from scipy.stats import chi2

from bench.estimator.gating import nis_gate


@pytest.mark.parametrize("probability", [0.5, 0.95, 0.9999, 1 - 1e-9])
@pytest.mark.parametrize("dof", [1, 2, 3, 6])
def test_the_gate_is_the_chi_square_quantile(probability, dof):
    assert nis_gate(probability, dof) == pytest.approx(chi2.ppf(probability, dof), rel=1e-12)
    # and it is the probability's quantile, read back through the distribution
    assert chi2.cdf(nis_gate(probability, dof), dof) == pytest.approx(probability, abs=1e-12)


@pytest.mark.parametrize("probability,dof,named", [(1.0, 3, "probability"), (0.0, 3, "probability"),
                                                   (0.99, 0, "dof")])
def test_a_gate_that_cannot_exist_is_named(probability, dof, named):
    with pytest.raises(ValueError, match=named):
        nis_gate(probability, dof)
