"""One leg of a simulated session, prepared as the pipeline prepares it: shared by the axis and clock tests."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from pipeline.axes import JointAxes, fit_joint_axes
from pipeline.params import WALKING
from pipeline.prepare import PreparedLeg, nominal_fs, prepare_leg_si, to_si
from pipeline.types import RawSensorStream
from pipeline.walking import fit_gyros


def leg_streams(streams: Sequence[RawSensorStream], leg: str, shank_lag_s: float = 0.0
                ) -> tuple[RawSensorStream, RawSensorStream]:
    """The leg's thigh and shank streams, the shank's stamps moved by ``shank_lag_s`` [s]."""
    thigh = next(s for s in streams if s.leg == leg and s.segment == "thigh")
    shank = next(s for s in streams if s.leg == leg and s.segment == "shank")
    return thigh, dataclasses.replace(shank, t_s=shank.t_s + shank_lag_s)


def prepared(thigh: RawSensorStream, shank: RawSensorStream
             ) -> tuple[PreparedLeg, np.ndarray, np.ndarray, JointAxes]:
    """The leg on its grid (walking preset), its fit gyros (N, 3) [rad/s] and its Eq. 2 axes (signs by
    :func:`pipeline.axes.orient_axes`)."""
    si1, si2 = to_si(thigh), to_si(shank)
    prep = prepare_leg_si(thigh.leg, si1, si2, nominal_fs(thigh, si1[0]), nominal_fs(shank, si2[0]),
                          params=WALKING.prepare)
    g1, g2 = fit_gyros(prep, WALKING.axes.fit_cutoff_hz)
    return prep, g1, g2, fit_joint_axes(g1, g2, prep.valid, WALKING.axes)
