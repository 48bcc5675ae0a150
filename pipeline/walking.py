"""One walking leg, prepared for the estimators: knee rate and shank sagittal rate about the fitted axes (Seel et al.
2014, Eq. 2-4), gait events (Allseits et al. 2018), joint centres (Eq. 5) and the accelerometer angle (Eq. 6-7)."""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.axes import (
    JointAxes,
    accelerometer_angle_deg,
    angular_acceleration,
    axis_up,
    centre_fit_step,
    fit_joint_axes,
    fit_joint_centres,
    fit_margin_mask,
    knee_excursion_deg,
    orient_thigh_on_gait,
    select_fit_samples,
)
from pipeline.bilateral import OtherLeg, gait_strides
from pipeline.leg_input import LegInput
from pipeline.params import PipelineParams
from pipeline.phases import GaitEvents, detect_gait_events
from pipeline.prepare import PreparedLeg
from pipeline.signal_utils import lowpass_runs_zeroed


def fit_gyros(prep: PreparedLeg, cutoff_hz: float, thigh: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Thigh and shank gyros (N, 3) [rad/s] low-passed at ``cutoff_hz`` for the fits, NaN-free. ``thigh``: the
    thigh's already, from :func:`reusable_thigh_fit`; then only the shank is filtered."""
    if thigh is not None:
        (g2,) = lowpass_runs_zeroed((prep.gyr_shank_rps,), prep.valid, cutoff_hz, prep.fs_hz)
        return thigh, g2
    g1, g2 = lowpass_runs_zeroed((prep.gyr_thigh_rps, prep.gyr_shank_rps), prep.valid, cutoff_hz, prep.fs_hz)
    return g1, g2


def reusable_thigh_fit(first: PreparedLeg, prep: PreparedLeg, thigh_fit: np.ndarray) -> np.ndarray | None:
    """The thigh's fit gyros of ``first`` (:func:`fit_gyros`) when they are also ``prep``'s: ``prep`` is the same leg
    with only the shank re-stamped, keeping ``first``'s whole grid, thigh channels and mask
    (:func:`pipeline.prepare.prepare_leg_si` with ``reuse``). The filter runs column by column, so filtering the
    thigh again would give the same values. None otherwise (a grid cut at its ends filters differently there)."""
    if prep.gyr_thigh_rps is first.gyr_thigh_rps and np.array_equal(prep.valid, first.valid):
        return thigh_fit
    return None


def gait_events(prep: PreparedLeg, axes: JointAxes, params: PipelineParams) -> tuple[np.ndarray, GaitEvents]:
    """Shank sagittal rate ``g2.j2`` (N,) [deg/s] (NaN where masked) and the gait events found on it (Allseits
    et al. 2018): they depend on the shank axis alone, not on the thigh axis's sign."""
    shank_sag = np.rad2deg(prep.gyr_shank_rps @ axes.j2)
    shank_sag[~prep.valid] = np.nan
    events = detect_gait_events(shank_sag, prep.fs_hz, prep.valid, shank_acc_mps2=prep.acc_shank_mps2,
                                params=params.phases)
    return shank_sag, events


def orient_on_gait(prep: PreparedLeg, axes: JointAxes, g1: np.ndarray, g2: np.ndarray, params: PipelineParams
                   ) -> JointAxes:
    """``axes`` with both signs turned where gait says the shank's was wrong: the sign under which the knee flexes
    away from extension over the strides found (:func:`pipeline.axes.knee_excursion_deg`, median over strides, each
    sign's gait events and its thigh sign from them, :func:`pipeline.axes.orient_thigh_on_gait`), when both signs find
    ``AxesParams.sign_min_strides`` strides at least and the turned one's figure is positive and
    ``AxesParams.sign_margin_deg`` above the given one's. Where the given sign finds fewer, nothing is turned (a step
    test alone: no stride under the given sign, three under the other, which would anchor a trace 12 deg off). The
    stride counts do not decide: a turn's small steps can give the wrong sign one or two strides more, and a walker's
    4 s cycles the given sign two only.

    Eq. 2 fixes the axes up to sign, and :func:`pipeline.axes.orient_axes` takes the shank's largest excursion as the
    forward swing. In step-to gait (crutches or a walker after a knee replacement) the leg that steps up beside the
    other flexes its knee 45-60 deg with a hip that moves 10-20: its shank turns backwards faster in early swing than
    it swings forwards (an independent simulator: -228 .. -317 against +200 .. +262 deg/s), so the largest excursion
    is the backward turn: taken for the swing, it leaves the leg no stride and its knee angle upside down. Its excursion
    figure reads -26 .. -39 deg with that sign and +26 .. +41 with the other (the leading leg +11 .. +29 against
    -11 .. -28), and its reciprocal walking +24 .. +30 against +2.5 .. +2.9; this repository's simulator's walking
    +19 .. +22 against +2 .. +5 (where the turned sign finds strides at all). ``g1``, ``g2``: the fit gyros
    (:func:`fit_gyros`)."""
    turned = dataclasses.replace(axes, j1=-axes.j1, j2=-axes.j2,
                                 hinge_j1=None if axes.hinge_j1 is None else -axes.hinge_j1,
                                 hinge_j2=None if axes.hinge_j2 is None else -axes.hinge_j2)
    scores: list[float] = []
    for candidate in (axes, turned):
        strides = gait_events(prep, candidate, params)[1].strides
        j1 = orient_thigh_on_gait(candidate.j1, candidate.j2, g1, g2, strides, prep.fs_hz)
        excursion = knee_excursion_deg(g1 @ j1, g2 @ candidate.j2, strides, prep.fs_hz)
        if excursion is None or excursion.size < params.axes.sign_min_strides:
            return axes
        scores.append(float(np.median(excursion)))
    return turned if scores[1] > max(scores[0] + params.axes.sign_margin_deg, 0.0) else axes


def build_walking_leg_input(prep: PreparedLeg, params: PipelineParams, axes: JointAxes | None = None,
                            fit_gyr: tuple[np.ndarray, np.ndarray] | None = None, thigh_fit: np.ndarray | None = None,
                            other: OtherLeg | None = None,
                            events: tuple[np.ndarray, GaitEvents] | None = None) -> LegInput:
    """Axes (unless given), rates, events, joint centres and accelerometer angle of one prepared leg.
    ``fit_gyr``: :func:`fit_gyros` of this very ``prep`` when already computed (:func:`pipeline.sync.synchronised_leg`),
    so the same filter is not run twice; else ``thigh_fit``, the thigh's half of it (:func:`reusable_thigh_fit`).
    ``other``: the contralateral leg's swings; only the strides that alternate
    with them (:func:`pipeline.bilateral.gait_strides`) decide the thigh axis's sign. ``events``: :func:`gait_events`
    of this ``prep`` and ``axes`` when already computed (the other leg's alternation check needs them first)."""
    valid = prep.valid
    fs = prep.fs_hz
    cutoff = params.axes.fit_cutoff_hz
    g1, g2 = fit_gyros(prep, cutoff, thigh=thigh_fit) if fit_gyr is None else fit_gyr
    if axes is None:
        axes = fit_joint_axes(g1, g2, prep.measured(), params.axes, up=axis_up(prep, params.axes))
    rate = np.rad2deg(prep.gyr_thigh_rps @ axes.j1 - prep.gyr_shank_rps @ axes.j2)
    rate[~valid] = np.nan
    shank_sag, ev = gait_events(prep, axes, params) if events is None else events
    # the thigh axis's sign again, from gait alone: non-gait movements between bouts can outweigh gait in the
    # whole-session rule (pipeline.axes.orient_thigh_on_gait); the shank's sign already found the strides. Jumps
    # and squats in a row look like strides of one leg; only the other leg's anti-phase swing tells gait from them,
    # so they never vote (pipeline.bilateral)
    gait = gait_strides(prep.t_s, ev.strides, ev.ms, other)
    j1 = orient_thigh_on_gait(axes.j1, axes.j2, g1, g2, gait, fs)
    if j1 is not axes.j1:
        axes = dataclasses.replace(axes, j1=j1)
        rate = np.rad2deg(prep.gyr_thigh_rps @ axes.j1 - prep.gyr_shank_rps @ axes.j2)
        rate[~valid] = np.nan
    a1, a2 = lowpass_runs_zeroed((prep.acc_thigh_mps2, prep.acc_shank_mps2), valid, cutoff, fs)
    gd1, gd2 = angular_acceleration(g1, fs), angular_acceleration(g2, fs)
    # joint centres only tell standing from sitting (upright test of the standing reference, pipeline.posture):
    # their in-plane directions are too uncertain for the absolute zero itself.
    # Fit samples stay away from masked gaps: the filters and Eq. 1 differences are unreliable within a few samples.
    far = fit_margin_mask(valid, fs, params.axes)
    idx = select_fit_samples(g1, g2, far, params.axes, step=centre_fit_step(fs, params.axes))
    centres = fit_joint_centres(a1[idx], g1[idx], gd1[idx], a2[idx], g2[idx], gd2[idx], axes.j1, axes.j2,
                                params.axes)
    acc_angle = accelerometer_angle_deg(a1, g1, gd1, a2, g2, gd2, axes.j1, axes.j2, centres)
    acc_angle[~valid] = np.nan
    return LegInput(prep=prep, axes=axes, centres=centres, rate_dps=rate, acc_angle_deg=acc_angle,
                    shank_sag_dps=shank_sag, events=ev, params=params, activity="walking")
