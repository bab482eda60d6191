"""A value printed with its standard deviation, to as many decimals as the sigma needs."""
from __future__ import annotations

import math


def plus_minus(value: float, sigma: float, unit: str = "", signed: bool = True, digits: int = 0) -> str:
    """``value +- sigma`` (each followed by ``unit``) with at least ``digits`` decimals and at least
    as many as show the sigma's first two significant digits, so that no sigma prints as zero
    (a time offset fixed to 3e-5 s is ``+0.021400 +- 0.000030``, not ``+0.0214 +- 0.0000``).
    A sigma that is zero or not finite is printed with ``digits`` decimals, or 3 where that is 0."""
    if math.isfinite(sigma) and sigma > 0:
        digits = max(digits, 1 - math.floor(math.log10(sigma)))
    elif digits == 0:
        digits = 3
    return f"{value:{'+' if signed else ''}.{digits}f}{unit} +- {sigma:.{digits}f}{unit}"
