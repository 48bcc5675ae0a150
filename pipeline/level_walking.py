"""Level walking keeps the knee near extension through stance: a stair step does not.

From initial contact to terminal stance a level-walking knee stays within ~20 deg of its straightest: it flexes
10-25 deg in loading response and extends again (Perry and Burnfield 2010, Ch. 4; the loading flexion grows with
speed, Lelas et al. 2003), and it is near extension again in terminal swing; only pre-swing and swing take it far
from there. Stair gait loads a flexed knee: ascent makes contact at 50-60 deg and extends under load, descent makes
contact near extension and flexes under load to ~75 deg before toe-off (Riener et al. 2002, Protopapadaki et al.
2007). So the share of a stride spent within ``PhaseParams.level_band_deg`` of its own minimum separates the two
without any absolute level: 0.59-0.68 on the real biomechZoo trial (its Vicon angles 0.68-0.71), 0.61-0.80 over
the simulator's walking patterns (fast to stiff-knee and crouch, 3-D knees, 50 Hz, turns, loss); 0.29-0.41 in its
stair flights. Running never stays near extension (a running leg is not judged). The strides that lead onto or
off a stair step are transitions, neither (:func:`next_to`): the last one before a flight lifts the foot onto the
first step, the first one after it takes its stance on the last.

Where the stance holds long pauses (a step test: up onto a step, both feet on it, down again) the knee rests near
extension for most of the stride and the share passes. What still tells a step down from a step of level gait is
where the knee flexes most: level walking flexes it most in swing (60-70 deg) and only 10-25 deg in loading
response, while lowering the body off a step flexes the stance knee to 60-75 deg under load and swings a nearly
straight leg (:func:`stance_above_swing`). Over every stride of this repository's simulator's walking patterns, the
real trial and two independent simulators' gait, step-to gait and sit-to-stand between walks, the stance never
flexed beyond the swing's peak (0.0 deg); an independent simulator's step-downs flexed 37-39 deg beyond it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pipeline.types import StrideValues


def near_extension_share(angle_deg: np.ndarray, t_s: np.ndarray, spans_s: np.ndarray, band_deg: float
                         ) -> np.ndarray:
    """Per stride ``[t_start, t_end)`` (rows of ``spans_s`` [s]), the share of its finite samples of
    ``angle_deg`` (N,) on the grid ``t_s`` (N,) [s] that lie within ``band_deg`` of the stride's own minimum; NaN
    for a stride without finite samples. Linear in the strides' total length."""
    spans = np.asarray(spans_s, dtype=float).reshape(-1, 2)
    lo, hi = np.searchsorted(t_s, spans[:, 0]), np.searchsorted(t_s, spans[:, 1])
    out = np.full(spans.shape[0], np.nan)
    for k, (a, b) in enumerate(zip(lo, hi, strict=True)):
        seg = angle_deg[a:b]
        seg = seg[np.isfinite(seg)]
        if seg.size:
            out[k] = np.count_nonzero(seg < seg.min() + band_deg) / seg.size
    return out


def not_level_walking(angle_deg: np.ndarray, t_s: np.ndarray, spans_s: np.ndarray, band_deg: float,
                      min_share: float) -> list[int]:
    """Indices of the strides (rows ``[t_start, t_end)`` of ``spans_s`` [s]) whose knee stays near extension for
    less than ``min_share`` of the stride (:func:`near_extension_share`): stair or step-like, not level gait."""
    share = near_extension_share(angle_deg, t_s, spans_s, band_deg)
    return np.flatnonzero(share < min_share).tolist()


def stance_above_swing(strides: Sequence[StrideValues], margin_deg: float) -> list[int]:
    """Indices of the strides whose knee flexes more in stance than at its swing peak, by more than ``margin_deg``
    [deg]: the stride's range (its largest flexion less its least) beyond its swing peak less its least. A step
    down, not level gait."""
    return [k for k, s in enumerate(strides)
            if s.rom_deg - (s.peak_swing_flexion_deg - s.min_flexion_deg) > margin_deg]


def next_to(spans_s: np.ndarray, idx: list[int] | set[int], tol_s: float = 0.02) -> list[int]:
    """Indices of the strides (rows ``[t_start, t_end)`` of ``spans_s`` [s]) not in ``idx`` that share a heel strike
    (within ``tol_s``) with one in ``idx``: the strides next to them in their bout."""
    spans = np.asarray(spans_s, dtype=float).reshape(-1, 2)
    marked = np.zeros(spans.shape[0], dtype=bool)
    marked[list(idx)] = True
    if not marked.any():
        return []
    ends, starts = spans[marked, 1], spans[marked, 0]
    touch = (np.abs(spans[:, 0, None] - ends[None, :]) <= tol_s).any(axis=1) | \
        (np.abs(spans[:, 1, None] - starts[None, :]) <= tol_s).any(axis=1)
    return np.flatnonzero(touch & ~marked).tolist()
