"""The chi-square gate an estimator holds a measurement's normalised innovation squared (NIS) to."""
from __future__ import annotations

from functools import lru_cache

from scipy.special import chdtri


@lru_cache(maxsize=None)
def nis_gate(probability: float, dof: int) -> float:
    """The NIS above which a measurement is rejected: the chi-square quantile with
    P(chi2_dof <= gate) = probability, for a measurement of `dof` components.

    scipy.special's inverse survival function rather than scipy.stats.chi2.ppf: the same number,
    and importing scipy.stats cost every bench run 0.4 s of start-up."""
    if not 0.0 < probability < 1.0:
        raise ValueError(f"gate probability must be in (0, 1), got {probability}")
    if dof < 1:
        raise ValueError(f"a measurement has at least one component, got dof {dof}")
    return float(chdtri(dof, 1.0 - probability))
