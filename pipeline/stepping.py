"""A step carries the thigh forward through the swing; lowering a lifted leg turns it back, a side step hardly at all.

In gait the hip flexes through the swing, from 10-20 deg of extension at toe-off to 25-35 deg of flexion before heel
strike (Perry and Burnfield 2010, Ch. 4; running: Novacheck 1998), so the thigh turns forward while the shank swings
forward. Marching in place lifts the leg by flexing hip and knee together and then lowers it: as the knee extends the
shank swings forward, but the thigh comes down, turning back as far as it was lifted. The shank's rate cannot tell
the two apart (both are a forward lobe between a backward turn and a foot contact, :mod:`pipeline.phases`); the
thigh's over the same interval can, from the gyroscope alone and without any absolute level.

Side steps, which carry the foot sideways, turn the thigh hardly at all in the sagittal plane. So a step's thigh
turns forward over its swing, and zero is the bound (``PhaseParams.min_swing_thigh_deg``).

The swing is read from the detected toe-off, the start of the shank's forward lobe. In running that lies well
after the true toe-off (the knee flexes fast in early swing and the shank keeps turning back), and the thigh
retracts before the foot strikes (Novacheck 1998), so from the detected toe-off it may turn back a little although
the leg ran forward: -6 .. +5 deg over an independent simulator's running strides, 19-40 % of them below zero. What
still tells a step is where the thigh lands: at the next heel strike it stands forward of its most extended in the
stride (push-off) by 16-50 deg in those running strides and 4-50 in this repository's walking patterns (the least a
shuffle with a stiff hip), while a lowered leg lands where it stood (marching 0 .. +3 deg on both simulators). A
stride is no step when it fails both: its thigh turns back over the swing and lands less than
``PhaseParams.min_contact_thigh_deg`` forward of its most extended.

Over each detected stride's swing (toe-off to the next heel strike): the real biomechZoo trial +30 .. +36 deg; this
repository's simulator's walking patterns (slow, fast, crouch, stiff-knee, a stiff hip at half its excursion, paces
down to 0.4, 3-D hips and knees, turns) and running +4 .. +52, a single stride at a bout's end -3; an independent
simulator's gait (normal, slow, a shuffle, crouch, high-knee gait) +3 .. +48. Marching in place -35 .. -39 (the
independent simulator's -24 .. -32 where its events fell on the lowering), the strides that span a jump's landing
-31 .. -35, the independent simulator's side steps -2 .. -6.
"""

from __future__ import annotations

import numpy as np

from pipeline.params import PhaseParams


def thigh_swing_deg(thigh_sag_dps: np.ndarray, strides: list[tuple[int, int, int]], fs_hz: float) -> np.ndarray:
    """Per stride ``(hs, to, hs_next)`` (sample indices), the thigh's rotation [deg] from toe-off to the next heel
    strike: its sagittal rate ``thigh_sag_dps`` (N,) [deg/s, sampled at ``fs_hz``, forward positive, NaN where
    masked] summed over the swing, masked samples left out. (strides,) array."""
    return _swing_deg(_summed(thigh_sag_dps), strides, fs_hz)


def thigh_landing_deg(thigh_sag_dps: np.ndarray, strides: list[tuple[int, int, int]], fs_hz: float) -> np.ndarray:
    """Per stride ``(hs, to, hs_next)`` (sample indices), how far forward [deg] the thigh stands at the next heel
    strike of where it was most extended within the stride: its sagittal rate ``thigh_sag_dps`` (N,) [deg/s, sampled
    at ``fs_hz``, forward positive, NaN where masked] integrated, masked samples left out, from ``hs`` through the
    strike's own sample (as :func:`thigh_swing_deg`). Never negative. (strides,) array."""
    return _landing_deg(_summed(thigh_sag_dps), strides, fs_hz)


def lowered_not_stepped(thigh_sag_dps: np.ndarray, strides: list[tuple[int, int, int]], fs_hz: float,
                        params: PhaseParams) -> set[int]:
    """Indices of the strides whose thigh turns forward by less than ``params.min_swing_thigh_deg`` [deg] over the
    swing (:func:`thigh_swing_deg`) and lands less than ``params.min_contact_thigh_deg`` forward of its most extended
    (:func:`thigh_landing_deg`): a lifted leg lowered in place or a side step, not a step forward."""
    cum = _summed(thigh_sag_dps)
    back = np.flatnonzero(_swing_deg(cum, strides, fs_hz) < params.min_swing_thigh_deg)
    if back.size == 0:
        return set()
    landing = _landing_deg(cum, [strides[k] for k in back], fs_hz)
    return set(back[landing < params.min_contact_thigh_deg].tolist())


def _summed(rate_dps: np.ndarray) -> np.ndarray:
    """(N + 1,) running sum of ``rate_dps`` (N,) from 0, masked (NaN) samples adding nothing: entry ``i`` sums the
    samples before ``i``."""
    return np.concatenate(([0.0], np.cumsum(np.nan_to_num(rate_dps, nan=0.0))))


def _swing_deg(cum: np.ndarray, strides: list[tuple[int, int, int]], fs_hz: float) -> np.ndarray:
    """:func:`thigh_swing_deg` from the rate's running sum ``cum`` (:func:`_summed`)."""
    out = np.zeros(len(strides))
    for k, (_, to, hs_next) in enumerate(strides):
        out[k] = (cum[hs_next + 1] - cum[to]) / fs_hz
    return out


def _landing_deg(cum: np.ndarray, strides: list[tuple[int, int, int]], fs_hz: float) -> np.ndarray:
    """:func:`thigh_landing_deg` from the rate's running sum ``cum`` (:func:`_summed`)."""
    angle = cum / fs_hz
    out = np.zeros(len(strides))
    for k, (hs, _, hs_next) in enumerate(strides):
        out[k] = angle[hs_next + 1] - angle[hs:hs_next + 2].min()
    return out
