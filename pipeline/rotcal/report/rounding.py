"""Rounding a result as the GUM asks (JCGM 100:2008, 7.2.6): the
uncertainty to at most two significant digits, the value to the same
decimal place. One function for every page rotcal writes for people
(the certificate, report.md)."""

from __future__ import annotations

import math

SIGNIFICANT_DIGITS = 2


def decimals_for(uncertainty: float, digits: int = SIGNIFICANT_DIGITS) -> int:
    """Decimal places that leave ``digits`` significant digits of
    ``uncertainty`` after rounding (negative: tens, hundreds, ...). A
    rounding that carries into a new digit (0.0996 -> 0.10) keeps the
    place of the carried result, so 0.0996 gives 2 places, not 3."""
    places = digits - 1 - math.floor(math.log10(uncertainty))
    if round(uncertainty, places) >= 10.0 ** (digits - places):
        places -= 1
    return places


def _fixed(x: float, places: int) -> str:
    rounded = round(x, places) + 0.0  # + 0.0: no "-0.000" for a value that rounds to zero
    return f"{rounded:.{max(places, 0)}f}"


def gum_round(value: float, uncertainty: float, digits: int = SIGNIFICANT_DIGITS) -> tuple[str, str]:
    """``value`` and ``uncertainty`` as text, the uncertainty with ``digits``
    significant digits and the value to the same decimal place (GUM 7.2.6):
    (1671.41234, 0.0491) -> ("1671.412", "0.049"). An uncertainty that is
    zero or not finite gives no place to round to: the value keeps six
    significant digits and the uncertainty reads as it is."""
    if not (math.isfinite(uncertainty) and uncertainty > 0):
        return f"{value:.6g}", f"{uncertainty:g}"
    places = decimals_for(uncertainty, digits)
    return _fixed(value, places), _fixed(uncertainty, places)


def gum_text(value: float, uncertainty: float, digits: int = SIGNIFICANT_DIGITS) -> str:
    """``"value ± uncertainty"`` rounded by ``gum_round``."""
    v, u = gum_round(value, uncertainty, digits)
    return f"{v} ± {u}"
