"""The normal and Student-t functions of the control charts and the interval methods, from
``scipy.special``: the numbers ``scipy.stats`` gives (its ``norm.cdf``, ``norm.sf`` and ``t.ppf`` are
these special functions behind argument checks, reproduced here; ``tests/test_special_functions.py`` compares them
bit for bit over a grid), without importing ``scipy.stats``: about 0.6 s of CPU that the daemon's
first history (``station.lab.history``), which needs only these, would pay otherwise.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.special import ndtr, stdtrit


def norm_cdf(x: Any) -> Any:
    """Standard normal distribution function of ``x`` (scalar or array), as ``scipy.stats.norm.cdf``."""
    return ndtr(x)


def norm_sf(x: Any) -> Any:
    """Standard normal survival function 1 - Φ(x) of ``x``, as ``scipy.stats.norm.sf`` (Φ(-x))."""
    return ndtr(np.negative(x))


def t_ppf(q: Any, df: Any) -> Any:
    """Student-t quantile of probability ``q`` with ``df`` degrees of freedom, as
    ``scipy.stats.t.ppf``: NaN for df <= 0 or q outside [0, 1], -inf at q = 0 (the lower end of the
    support, where ``stdtrit`` gives +inf)."""
    q_, df_ = np.asarray(q, dtype=float), np.asarray(df, dtype=float)
    out = np.where((q_ == 0) & (df_ > 0), -np.inf, stdtrit(df_, q_))
    return out[()]
