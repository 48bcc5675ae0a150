"""Extended Kalman filter for the knee flexion angle (Rhudy et al. 2024, Sect. 2.3.2 and 2.4.2, Eq. 13-15, 22-24).

State ``x = alpha``, input ``u = g1.j1 - g2.j2`` as in the KF (Eq. 20, ``F = 1``). The measurement is the
lever-arm-corrected thigh acceleration in the joint plane, predicted by rotating the shank acceleration by the knee
angle (Eq. 23): ``[a2.x2, a2.y2] = Rot(x) [a1.x1, a1.y1]`` (Rhudy numbering: 1 shank, 2 thigh), Jacobian Eq. 24.
``R`` is diagonal (``r_x``, ``r_y`` in (m/s^2)^2). This package numbers the thigh 1 and the shank 2 and measures
flexion as (angle of the shank's knee acceleration) - (angle of the thigh's) (:mod:`pipeline.axes`), so here the
ROTATED vector ``acc_a`` is the thigh's and the MEASURED ``acc_b`` the shank's: ``b = Rot(alpha) a``.

Why it behaves like a KF with a data-dependent gain: with ``r_x = r_y = r`` the update is
``x += P |a1| |a2| / (P |a1|^2 + r) * sin(alpha_acc - x)``, i.e. the accelerometer angle weighted by the
acceleration magnitudes. The default ``r`` is therefore the KF's ``R`` (deg^2) times ``g^2`` in rad^2 units, so both
filters have the same time constant ``tau_s`` when the segments see about 1 g.

The recursion is nonlinear in the state, so it runs as one scalar loop (pure Python floats, no numpy per sample):
about 0.2 s for a 10-minute leg at 200 Hz.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.axes import angular_acceleration, gamma_apply, joint_plane_frames
from pipeline.constants import G_MPS2
from pipeline.estimators.kf import (
    FILTER_TAU_S,
    R_DEG2,
    FilterDiagnostics,
    filter_setup,
    interval_rate,
    q_for_time_constant,
    start_from_measurement,
)
from pipeline.filter_inputs import debiased_rate, r_scale, run_per_segment, update_mask
from pipeline.leg_input import LegInput
from pipeline.signal_utils import lowpass_runs_zeroed

DEG2_TO_RAD2 = math.radians(1.0) ** 2


def r_mps2_sq(r_deg2: float) -> float:
    """The KF's accelerometer-angle variance [deg^2] as the EKF's acceleration variance [(m/s^2)^2] at 1 g."""
    return r_deg2 * DEG2_TO_RAD2 * G_MPS2**2


R_MPS2_SQ = r_mps2_sq(R_DEG2)


def ekf_angle(rate_dps: np.ndarray, acc_a_plane_mps2: np.ndarray, acc_b_plane_mps2: np.ndarray,
              fs_hz: float, *, tau_s: float = FILTER_TAU_S, r_x_mps2_sq: float = R_MPS2_SQ,
              r_y_mps2_sq: float | None = None, update_mask: np.ndarray | None = None,
              x0_deg: float | None = None, p0_deg2: float | None = None,
              r_scale: np.ndarray | None = None, force_general: bool = False) -> np.ndarray:
    """Knee flexion (deg) by the EKF of Rhudy et al. Eq. 22-24.

    ``acc_*_plane_mps2`` are (N, 2): the lever-arm-corrected accelerations projected on each segment's joint-plane
    axes ``(x_i, y_i)`` of Eq. 7, with ``b = Rot(alpha) a``. ``tau_s`` sets Q as in the KF, with R's angle
    equivalent ``r_x / g^2``. ``update_mask`` False skips the measurement update (impacts, NaN samples).
    Without ``x0_deg`` the state starts where the first second of usable accelerometer angles puts it
    (:func:`pipeline.estimators.kf.start_from_measurement`, variance ``R_DEG2``). ``r_scale`` (per sample)
    multiplies R, as in :func:`pipeline.estimators.kf.kf_angle`.
    With ``r_x = r_y`` an exactly equivalent, faster form runs unless ``force_general``."""
    rate = interval_rate(np.asarray(rate_dps, dtype=float))
    a1 = np.asarray(acc_a_plane_mps2, dtype=float).reshape(-1, 2)
    a2 = np.asarray(acc_b_plane_mps2, dtype=float).reshape(-1, 2)
    n = rate.shape[0]
    if a1.shape[0] != n or a2.shape[0] != n:
        raise ValueError("rate and accelerations differ in length")
    if n == 0:
        return np.empty(0)
    finite = np.isfinite(a1).all(axis=1) & np.isfinite(a2).all(axis=1)
    mask = finite if update_mask is None else np.asarray(update_mask, dtype=bool) & finite
    dt = 1.0 / fs_hz
    rx = float(r_x_mps2_sq)
    ry = rx if r_y_mps2_sq is None else float(r_y_mps2_sq)
    q = q_for_time_constant(tau_s, fs_hz, 0.5 * (rx + ry) / G_MPS2**2)
    # the angle from a to b (Eq. 23's measurement as one angle): the start value's and the isotropic loop's
    theta = np.arctan2(a1[:, 0] * a2[:, 1] - a1[:, 1] * a2[:, 0], a1[:, 0] * a2[:, 0] + a1[:, 1] * a2[:, 1])
    if x0_deg is None:
        x = math.radians(start_from_measurement(np.degrees(theta), mask, rate_dps, dt))
    else:
        x = math.radians(x0_deg)
    p = DEG2_TO_RAD2 * (R_DEG2 if p0_deg2 is None else p0_deg2)
    du = (np.radians(rate) * dt).tolist()
    scale = np.ones(n) if r_scale is None else np.broadcast_to(np.asarray(r_scale, float), (n,))
    if rx == ry and not force_general:
        out = _isotropic_loop(x, p, q, rx, du, mask, scale, a1, a2, theta)
    else:
        out = _general_loop(x, p, q, rx, ry, du, mask, scale, a1, a2)
    return np.degrees(np.asarray(out))


def _isotropic_loop(x: float, p: float, q: float, r: float, du: list[float], mask: np.ndarray, scale: np.ndarray,
                    a1: np.ndarray, a2: np.ndarray, theta: np.ndarray) -> list[float]:
    """Eq. 15 with R = r I, simplified exactly: H = Rot(x + 90 deg) a is orthogonal to h(x) = Rot(x) a and has
    |H| = |a|, so (Sherman-Morrison) K = P H^T / (P |a|^2 + r) and the update is
    ``x += P |a| |b| / (P |a|^2 + r) * sin(theta - x)``, ``P *= r / (P |a|^2 + r)``, theta the angle from a to b
    (``theta`` (N,) [rad], precomputed for all samples). About twice as fast as the general loop."""
    n = len(du)
    aa = np.einsum("ij,ij->i", a1, a1)
    ab = np.sqrt(aa * np.einsum("ij,ij->i", a2, a2))
    aa_l, ab_l, th_l = aa.tolist(), ab.tolist(), theta.tolist()
    rs_l = (r * scale).tolist()
    mask_l = mask.tolist()
    out = [0.0] * n
    sin = math.sin
    for k in range(n):
        if k > 0:
            x += du[k - 1]
            p += q
        if mask_l[k]:
            d = p * aa_l[k] + rs_l[k]
            x += p * ab_l[k] / d * sin(th_l[k] - x)
            p *= rs_l[k] / d
        out[k] = x
    return out


def _general_loop(x: float, p: float, q: float, rx: float, ry: float, du: list[float], mask: np.ndarray,
                  scale: np.ndarray, a1: np.ndarray, a2: np.ndarray) -> list[float]:
    """Eq. 15 literally, with the observation of Eq. 23 and its Jacobian Eq. 24, for a diagonal R."""
    n = len(du)
    mask_l = mask.tolist()
    scale_l = scale.tolist()
    s1x, s1y = a1[:, 0].tolist(), a1[:, 1].tolist()
    t2x, t2y = a2[:, 0].tolist(), a2[:, 1].tolist()
    out = [0.0] * n
    cos, sin = math.cos, math.sin
    for k in range(n):
        if k > 0:
            x += du[k - 1]  # Eq. 15 prediction with f = x + dt u (Eq. 20), F = 1
            p += q
        if mask_l[k]:
            c, s = cos(x), sin(x)
            ax, ay = s1x[k], s1y[k]
            # h(x) = Rot(x) a (Eq. 23) and its Jacobian H (Eq. 24)
            hx, hy = c * ax - s * ay, s * ax + c * ay
            jx, jy = -s * ax - c * ay, c * ax - s * ay
            # S = H P H^T + R (2x2), K = P H^T S^-1 (1x2)
            sc = scale_l[k]
            s11, s12, s22 = p * jx * jx + rx * sc, p * jx * jy, p * jy * jy + ry * sc
            det = s11 * s22 - s12 * s12
            kx = p * (jx * s22 - jy * s12) / det
            ky = p * (jy * s11 - jx * s12) / det
            x += kx * (t2x[k] - hx) + ky * (t2y[k] - hy)
            p *= 1.0 - (kx * jx + ky * jy)
        out[k] = x
    return out


def plane_accelerations(leg: LegInput) -> tuple[np.ndarray, np.ndarray]:
    """Lever-arm-corrected accelerations (Eq. 6) of thigh and shank in their joint-plane frames (Eq. 7), (N, 2)
    each [m/s^2], filtered as for the leg's accelerometer angle (``AxesParams.fit_cutoff_hz``; a ``prefiltered``
    leg, running, comes already 7 Hz filtered)."""
    prep, fs = leg.prep, leg.fs_hz
    if leg.prefiltered:
        g1, g2, a1, a2 = prep.gyr_thigh_rps, prep.gyr_shank_rps, prep.acc_thigh_mps2, prep.acc_shank_mps2
    else:
        g1, g2, a1, a2 = lowpass_runs_zeroed(
            (prep.gyr_thigh_rps, prep.gyr_shank_rps, prep.acc_thigh_mps2, prep.acc_shank_mps2), prep.valid,
            leg.params.axes.fit_cutoff_hz, fs)
    centres = leg.centres
    j1, j2 = leg.axes.j1, leg.axes.j2
    x1, x2 = joint_plane_frames(centres, j1, j2)
    y1, y2 = np.cross(j1, x1), np.cross(j2, x2)
    at1 = a1 - gamma_apply(g1, angular_acceleration(g1, fs), centres.o1)
    at2 = a2 - gamma_apply(g2, angular_acceleration(g2, fs), centres.o2)
    return np.column_stack([at1 @ x1, at1 @ y1]), np.column_stack([at2 @ x2, at2 @ y2])


def ekf_leg(leg: LegInput, tau_s: float | None = None) -> tuple[np.ndarray, FilterDiagnostics]:
    """EKF knee angle (N,) [deg] of one leg, with the KF's inputs (de-biased rate, update mask, quiet-standing
    weighting, zero from standing) and its automatically tuned time constant unless ``tau_s`` is given."""
    tau, diag, quiet = filter_setup(leg, tau_s)
    rate = debiased_rate(leg)
    mask = update_mask(leg)
    scale = r_scale(leg, quiet)
    zero = math.radians(diag.acc_zero_deg)
    thigh, shank = plane_accelerations(leg)
    # b = Rot(alpha + zero) a  ->  b = Rot(alpha) (Rot(zero) a): the standing zero moves into the thigh vector
    c, s = math.cos(zero), math.sin(zero)
    thigh = np.column_stack([c * thigh[:, 0] - s * thigh[:, 1], s * thigh[:, 0] + c * thigh[:, 1]])
    fs = leg.fs_hz
    r = r_mps2_sq(leg.params.kf.r_deg2)
    angle = run_per_segment(leg, lambda a, b: ekf_angle(rate[a:b], thigh[a:b], shank[a:b], fs, tau_s=tau,
                                                        r_x_mps2_sq=r, update_mask=mask[a:b],
                                                        r_scale=scale[a:b]), mask)
    return angle, diag
