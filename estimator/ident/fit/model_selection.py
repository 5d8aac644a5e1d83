"""Model selection between the plain and the robust cost (likelihood ratio, chi-square with 6 dof).

The robust cost adds the nuisance span (:mod:`estimator.ident.fit.cost`) to the plain model, so the
two are nested: under a correct model ``(RSS_plain - RSS_robust) / sigma^2`` is chi-square with as
many degrees of freedom as the span has columns. Far beyond that, the plain fit is absorbing a
smooth model error in its (N_u, L_h) and the robust estimate is the one to use.
"""

from __future__ import annotations

import math

from estimator.ident.fit.cost import CostModel, noise_sigma_v
from estimator.ident.fit.local_fit import LocalFit


def likelihood_ratio(m_plain: CostModel, f_plain: LocalFit, m_rob: CostModel, f_rob: LocalFit) -> float:
    """(RSS_plain − RSS_robust) / sigma^2 over the plain model's window (NaN if a fit failed).

    The robust fit's residual over the plain window is projected with the plain window's basis,
    so both sums are over the same samples; sigma is the noise level of the robust residual.
    """
    if not (f_plain.success and f_rob.success):
        return float("nan")
    n = m_plain.n
    r_plain = f_plain.residual[:n]
    r_rob = f_rob.residual[:n]
    r_rob = m_plain.without_nuisance(r_rob)
    sigma = noise_sigma_v(r_rob)
    return float(r_plain @ r_plain - r_rob @ r_rob) / sigma ** 2


def prefers_robust(stat: float, threshold: float) -> bool:
    """True if the likelihood-ratio statistic says the plain model is wrong (beyond ``threshold``)."""
    return math.isfinite(stat) and stat > threshold
