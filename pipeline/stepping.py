"""A step carries the thigh forward through the swing; lowering a lifted leg turns it back, a side step hardly at all.

In gait the hip flexes through the swing, from 10-20 deg of extension at toe-off to 25-35 deg of flexion before heel
strike (Perry and Burnfield 2010, Ch. 4; running: Novacheck 1998), so the thigh turns forward while the shank swings
forward. Marching in place lifts the leg by flexing hip and knee together and then lowers it: as the knee extends the
shank swings forward, but the thigh comes down, turning back as far as it was lifted. The shank's rate cannot tell
the two apart (both are a forward lobe between a backward turn and a foot contact, :mod:`pipeline.phases`); the
thigh's over the same interval can, from the gyroscope alone and without any absolute level.

Side steps, which carry the foot sideways, turn the thigh hardly at all in the sagittal plane. So a step's thigh
turns forward over its swing, and zero is the bound (``PhaseParams.min_swing_thigh_deg``).

Over each detected stride's swing (toe-off to the next heel strike): the real biomechZoo trial +30 .. +36 deg; this
repository's simulator's walking patterns (slow, fast, crouch, stiff-knee, a stiff hip at half its excursion, paces
down to 0.4, 3-D hips and knees, turns) and running +4 .. +52, a single stride at a bout's end -3; an independent
simulator's gait (normal, slow, a shuffle, crouch, high-knee gait) +3 .. +48. Marching in place -35 .. -39 (the
independent simulator's -24 .. -32 where its events fell on the lowering), the strides that span a jump's landing
-31 .. -35, the independent simulator's side steps -2 .. -6.
"""

from __future__ import annotations

import numpy as np


def thigh_swing_deg(thigh_sag_dps: np.ndarray, strides: list[tuple[int, int, int]], fs_hz: float) -> np.ndarray:
    """Per stride ``(hs, to, hs_next)`` (sample indices), the thigh's rotation [deg] from toe-off to the next heel
    strike: its sagittal rate ``thigh_sag_dps`` (N,) [deg/s, sampled at ``fs_hz``, forward positive, NaN where
    masked] summed over the swing, masked samples left out. (strides,) array."""
    cum = np.concatenate(([0.0], np.cumsum(np.nan_to_num(thigh_sag_dps, nan=0.0))))
    out = np.zeros(len(strides))
    for k, (_, to, hs_next) in enumerate(strides):
        out[k] = (cum[hs_next + 1] - cum[to]) / fs_hz
    return out


def lowered_not_stepped(thigh_sag_dps: np.ndarray, strides: list[tuple[int, int, int]], fs_hz: float,
                        min_swing_thigh_deg: float) -> set[int]:
    """Indices of the strides whose thigh turns forward by less than ``min_swing_thigh_deg`` [deg] over the swing
    (:func:`thigh_swing_deg`): a lifted leg lowered in place or a side step, not a step forward."""
    swing = thigh_swing_deg(thigh_sag_dps, strides, fs_hz)
    return set(np.flatnonzero(swing < min_swing_thigh_deg).tolist())
