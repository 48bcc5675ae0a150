"""Numbers the service hands out: finite or nothing, rounded to what the measurement supports."""

from __future__ import annotations

import math

import numpy as np


def finite_round(x: float | None, nd: int | None = 4) -> float | None:
    """``x`` rounded to ``nd`` decimals (``None``: as it is), or None when it is missing, NaN or infinite (JSON
    has no NaN)."""
    if x is None or not math.isfinite(x):
        return None
    return float(x) if nd is None else round(float(x), nd)


def json_safe(value: object) -> object:
    """Non-finite floats become None: PostgreSQL's JSON rejects NaN, and API clients cannot parse it either. numpy
    scalars become Python ones (the JSON encoder knows neither ``np.float64`` nor ``np.bool_``)."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value
