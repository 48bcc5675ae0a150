"""Per-stride knee metrics (heel strike to the next heel strike of the same leg), as reported by Allseits et al.
2018 (peak swing flexion, Sect. 2.4.2) and Potter et al. 2022 (range of motion per stride), plus temporal
parameters from the gait events."""

from __future__ import annotations

import numpy as np

from pipeline.params import WALKING, MetricsParams
from pipeline.types import StrideValues


def stride_values(angle_deg: np.ndarray, t_s: np.ndarray, hs: int, to: int, hs_next: int,
                  params: MetricsParams = WALKING.metrics) -> StrideValues:
    """Metrics of one stride ``[hs, hs_next]`` (sample indices) with toe-off ``to``; ``angle_deg`` (N,) must be
    finite on the stride, ``t_s`` (N,) its time stamps [s]."""
    seg = angle_deg[hs:hs_next + 1]
    swing = angle_deg[to:hs_next + 1]
    load_end = hs + max(int(round(params.loading_share * (to - hs))), 1)
    t0, t1, tt = float(t_s[hs]), float(t_s[hs_next]), float(t_s[to])
    peak = _nanmax(swing)
    low = _nanmin(seg)
    return StrideValues(
        t_start_s=t0, t_end_s=t1, duration_s=t1 - t0, t_toe_off_s=tt, stance_time_s=tt - t0, swing_time_s=t1 - tt,
        stance_pct=100.0 * (tt - t0) / (t1 - t0), peak_swing_flexion_deg=peak, min_flexion_deg=low,
        rom_deg=_nanmax(seg) - low, stance_flexion_deg=_nanmax(angle_deg[hs:load_end + 1]),
    )


# np.nanmax/np.nanmin cost ~10 us each (NaN masking copies); called per stride they dominated this module. Plain
# max/min give the same value whenever no NaN is present (they propagate a NaN, which triggers the NaN-aware call).
def _nanmax(x: np.ndarray) -> float:
    v = float(x.max())
    return float(np.nanmax(x)) if v != v else v


def _nanmin(x: np.ndarray) -> float:
    v = float(x.min())
    return float(np.nanmin(x)) if v != v else v
