"""Linear Kalman filter for the knee flexion angle (Rhudy et al. 2024, Sect. 2.3.1 and 2.4.1, Eq. 9-12, 18-21).

State ``x = alpha`` (knee flexion), input ``u = g1.j1 - g2.j2`` (relative angular rate about the joint axis),
measurement ``z = alpha_acc`` (the accelerometer angle of Seel et al. 2014, Rhudy Eq. 7). Eq. 20-21:
``x_k = x_{k-1} + dt * u_{k-1}``, ``F = 1``, ``G = dt``, ``H = 1``. Scalar ``Q`` (gyroscope uncertainty) and ``R``
(accelerometer-angle uncertainty); only their ratio shapes the estimate, so the tuning knob is the steady-state
fusion time constant ``tau_s`` (:func:`q_for_time_constant` maps it to Q).

Rhudy et al. skip the measurement update +-5 % of the gait cycle around each foot strike (``update_mask``).

The registered ``kf`` (:func:`kf_leg`) adds what the paper got from Vicon: no per-dataset tuning
(:mod:`pipeline.tuning`), no motion-capture initialisation (the state starts at the first usable accelerometer
angle carried back with the gyroscope, and R shrinks ``KfParams.quiet_r_scale``-fold while the leg is quiet, so
standing anchors the level), the accelerometer angle's zero from quiet upright standing (:mod:`pipeline.posture`),
and the gyro bias removed per stride (:mod:`pipeline.filter_inputs`).

Vectorised: the covariance recursion does not depend on the data, so the gain sequence is computed in closed form
per run of updates (a Moebius map with two fixed points), and the state recursion ``x_k = a_k x_{k-1} + b_k`` is
solved by cumulative products in blocks (:func:`linear_recursion`). :func:`kf_angle_loop` is the literal
Eq. 10-12 loop, kept as the reference the tests compare against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.filter_inputs import debiased_rate, r_scale, run_per_segment, update_mask
from pipeline.leg_input import EstimatorDiagnostics, LegInput
from pipeline.params import WALKING
from pipeline.posture import acc_zero_deg, leg_quiet
from pipeline.tuning import TuningDiagnostics, tune_time_constant

# defaults of the bare filter functions, from the walking preset (the leg-level estimators read ``leg.params.kf``)
R_DEG2 = WALKING.kf.r_deg2
FILTER_TAU_S = WALKING.kf.filter_tau_s
START_SPAN_S = WALKING.kf.start_span_s


def gain_for_time_constant(tau_s: float, fs_hz: float) -> float:
    """Steady-state gain of a first-order discrete low-pass with time constant ``tau_s``."""
    return float(1.0 - math.exp(-1.0 / (fs_hz * tau_s)))


def q_for_time_constant(tau_s: float, fs_hz: float, r: float = R_DEG2) -> float:
    """Per-sample process noise Q (Eq. 10) whose steady-state KF has fusion time constant ``tau_s``.

    At steady state the predicted variance solves ``P^2 - Q P - Q R = 0`` and ``K = P / (P + R)``, hence
    ``Q = R K^2 / (1 - K)``. Parametrising by ``tau_s`` keeps the filter's behaviour independent of the sampling
    rate (the paper's Q at R = 1, Fig. 10, is tied to its 400 Hz)."""
    k = gain_for_time_constant(tau_s, fs_hz)
    return r * k * k / (1.0 - k)


def time_constant_for_q(q: float, fs_hz: float, r: float = R_DEG2) -> float:
    """Inverse of :func:`q_for_time_constant`."""
    p = 0.5 * (q + math.sqrt(q * q + 4.0 * q * r))
    k = p / (p + r)
    return float(-1.0 / (fs_hz * math.log(1.0 - k)))


def interval_rate(rate_dps: np.ndarray) -> np.ndarray:
    """``u_{k-1}`` of Eq. 20 as the mean rate over ``[t_{k-1}, t_k]`` (trapezoid), so the first-order update does not
    lag the angle by half a sample (at 1000 deg/s swing rates and 200 Hz that lag alone is 2.5 deg)."""
    r = np.asarray(rate_dps, dtype=float)
    out = np.empty_like(r)
    out[:-1] = 0.5 * (r[:-1] + r[1:])
    out[-1:] = r[-1:]
    return out


def linear_recursion(a: np.ndarray, b: np.ndarray, x_init: float) -> np.ndarray:
    """Solve ``x_k = a_k * x_{k-1} + b_k`` (``x_{-1} = x_init``, ``0 < a_k <= 1``) without a Python loop per sample.

    Within a block ``x_k = A_k (x_start + sum_{j<=k} b_j / A_j)`` with ``A_k`` the running product of ``a``; blocks are
    short enough that ``A`` stays above 1e-80, and a loop over blocks carries the state across."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    n = a.shape[0]
    if n == 0:
        return np.empty(0)
    a = np.clip(a, 1e-12, 1.0)
    min_a = float(a.min())
    block = n if min_a >= 1.0 else max(1, min(n, int(80.0 * math.log(10.0) / -math.log(min_a))))
    n_blocks = -(-n // block)
    pad = n_blocks * block - n
    a2 = np.concatenate((a, np.ones(pad))).reshape(n_blocks, block)
    b2 = np.concatenate((b, np.zeros(pad))).reshape(n_blocks, block)
    cum_a = np.cumprod(a2, axis=1)
    local = cum_a * np.cumsum(b2 / cum_a, axis=1)
    starts = np.empty(n_blocks)
    x = float(x_init)
    ends_a = cum_a[:, -1].tolist()
    ends_local = local[:, -1].tolist()
    for i in range(n_blocks):
        starts[i] = x
        x = ends_a[i] * x + ends_local[i]
    return (local + cum_a * starts[:, None]).reshape(-1)[:n]


def _update_run_gains(p_pred0: float, n: int, q: float, r: float) -> tuple[np.ndarray, float]:
    """Gains of ``n`` consecutive measurement updates starting from predicted variance ``p_pred0``, and the posterior
    variance after the last one.

    Update then predict maps ``p -> p r / (p + r) + q = ((r+q) p + q r) / (p + r)``, a Moebius map with fixed points
    ``p+ > 0 > p-``; ``(p_k - p+) / (p_k - p-) = kappa^k (p_0 - p+) / (p_0 - p-)``, ``kappa = (p- + r) / (p+ + r)``."""
    disc = math.sqrt(q * q + 4.0 * q * r)
    p_plus, p_minus = 0.5 * (q + disc), 0.5 * (q - disc)
    kappa = (p_minus + r) / (p_plus + r)
    w0 = (p_pred0 - p_plus) / (p_pred0 - p_minus)
    w = w0 * kappa ** np.arange(n)
    p_pred = (p_plus - p_minus * w) / (1.0 - w)
    gains = p_pred / (p_pred + r)
    return gains, float(p_pred[-1] * r / (p_pred[-1] + r))


def kf_gains(update_mask: np.ndarray, q: float, r: float | np.ndarray, p0: float) -> np.ndarray:
    """Kalman gain per sample (0 where no update) for the scalar random-walk model, Eq. 10-12 with F = H = 1.

    ``r`` may vary per sample (piecewise constant: each run of equal ``r`` is solved in closed form). ``p0`` is the
    variance of the initial state before the first update; each sample after the first adds ``q``."""
    mask = np.asarray(update_mask, dtype=bool)
    n = mask.shape[0]
    r_arr = np.broadcast_to(np.asarray(r, dtype=float), (n,))
    gains = np.zeros(n)
    if n == 0:
        return gains
    change = np.flatnonzero((mask[1:] != mask[:-1]) | (r_arr[1:] != r_arr[:-1])) + 1
    bounds = np.concatenate(([0], change, [n])).tolist()
    p_pred = float(p0)  # predicted variance at the first sample of the current run
    for start, stop in zip(bounds[:-1], bounds[1:], strict=True):
        if mask[start]:
            gains[start:stop], p_post = _update_run_gains(p_pred, stop - start, q, float(r_arr[start]))
            p_pred = p_post + q
        else:
            p_pred += q * (stop - start)
    return gains


def start_from_measurement(z: np.ndarray, mask: np.ndarray, rate_dps: np.ndarray, dt: float,
                           span_s: float = START_SPAN_S) -> float:
    """Initial state [deg] at sample 0: the angle that best explains the usable accelerometer angles ``z`` of the
    first ``span_s`` after the first one, given the gyroscope's motion (median of accelerometer angle minus the
    rate's integral from sample 0). One sample's accelerometer angle in gait is off by the segment accelerations of
    that instant, several degrees; over ``span_s`` they average out while the integral's drift stays well below a
    degree (the walking CF starts the same way, :func:`pipeline.estimators.cf.complementary_filter`)."""
    first = np.flatnonzero(mask)
    if not first.size:
        return 0.0
    use = first[first < first[0] + max(int(round(span_s / dt)), 1)]
    moved = np.concatenate(([0.0], np.cumsum(interval_rate(rate_dps)[:-1]))) * dt
    return float(np.median(z[use] - moved[use]))


def kf_angle(rate_dps: np.ndarray, acc_angle_deg: np.ndarray, fs_hz: float, *,
             tau_s: float = FILTER_TAU_S, r_deg2: float = R_DEG2,
             update_mask: np.ndarray | None = None, x0_deg: float | None = None,
             p0_deg2: float | None = None, r_scale: np.ndarray | None = None) -> np.ndarray:
    """Knee flexion (deg) by the KF of Rhudy et al. Eq. 18-21.

    ``rate_dps``: relative angular rate about the joint axis (``g1.j1 - g2.j2``), ``acc_angle_deg``: the
    accelerometer angle (Eq. 7), ``update_mask``: where the accelerometer angle may update the state (False around
    foot strikes and where it is NaN). Initialisation needs no motion capture: ``x0_deg`` (e.g. the angle of a
    standing period) with variance ``p0_deg2``; without it the filter starts where the first second of usable
    accelerometer angles puts it (:func:`start_from_measurement`) with variance R. ``r_scale`` (per sample,
    default 1) multiplies R: the accelerometer angle is far more trustworthy while the leg is still (no segment
    accelerations) than in motion; Q stays set by ``tau_s``."""
    rate = np.asarray(rate_dps, dtype=float)
    z = np.asarray(acc_angle_deg, dtype=float)
    n = rate.shape[0]
    if z.shape[0] != n:
        raise ValueError("rate_dps and acc_angle_deg differ in length")
    if n == 0:
        return np.empty(0)
    dt = 1.0 / fs_hz
    q, r = q_for_time_constant(tau_s, fs_hz, r_deg2), r_deg2
    mask = np.isfinite(z) if update_mask is None else np.asarray(update_mask, dtype=bool) & np.isfinite(z)
    if x0_deg is None:
        x0_deg, p0_deg2 = start_from_measurement(z, mask, rate, dt), r
    p0 = r if p0_deg2 is None else float(p0_deg2)
    gains = kf_gains(mask, q, r if r_scale is None else r * np.asarray(r_scale, dtype=float), p0)
    u = interval_rate(rate)
    # x_k = (1-K_k) (x_{k-1} + dt u_{k-1}) + K_k z_k ; the sample-0 "prediction" is the initial state itself.
    drive = np.empty(n)
    drive[0] = 0.0
    drive[1:] = dt * u[:-1]
    z0 = np.where(mask, z, 0.0)
    a = 1.0 - gains
    b = a * drive + gains * z0
    return linear_recursion(a, b, float(x0_deg))


def kf_angle_loop(rate_dps: np.ndarray, acc_angle_deg: np.ndarray, fs_hz: float, *,
                  tau_s: float = FILTER_TAU_S, r_deg2: float = R_DEG2,
                  update_mask: np.ndarray | None = None, x0_deg: float | None = None,
                  p0_deg2: float | None = None, r_scale: np.ndarray | None = None) -> np.ndarray:
    """The same filter written literally as Eq. 10-12 (slow; the reference for :func:`kf_angle`)."""
    rate = np.asarray(rate_dps, dtype=float)
    z = np.asarray(acc_angle_deg, dtype=float)
    n = rate.shape[0]
    dt = 1.0 / fs_hz
    q, r = q_for_time_constant(tau_s, fs_hz, r_deg2), r_deg2
    mask = np.isfinite(z) if update_mask is None else np.asarray(update_mask, dtype=bool) & np.isfinite(z)
    if x0_deg is None:
        x0_deg, p0_deg2 = start_from_measurement(z, mask, rate, dt), r
    u = interval_rate(rate)
    r_k = np.broadcast_to(r if r_scale is None else r * np.asarray(r_scale, dtype=float), (n,))
    x, p = float(x0_deg), (r if p0_deg2 is None else float(p0_deg2))
    out = np.empty(n)
    for k in range(n):
        if k > 0:
            x = x + dt * u[k - 1]  # Eq. 10 with F = 1, G = dt
            p = p + q
        if mask[k]:
            gain = p / (p + r_k[k])  # Eq. 11, H = 1
            x = x + gain * (z[k] - x)  # Eq. 12
            p = (1.0 - gain) * p
        out[k] = x
    return out


@dataclass(frozen=True, kw_only=True)
class FilterDiagnostics(EstimatorDiagnostics):
    """KF/EKF/running-CF diagnostics: the time constant used and the accelerometer zero subtracted."""

    tuning: TuningDiagnostics | None  # None when the caller fixed ``tau_s``
    acc_zero_deg: float  # accelerometer reading of a straight knee, 0 without standing


def filter_setup(leg: LegInput, tau_s: float | None) -> tuple[float, FilterDiagnostics, np.ndarray]:
    """Time constant (tuned unless ``tau_s`` is given), the diagnostics and the quiet mask shared by the KF, EKF
    and running CF of one leg."""
    quiet = leg_quiet(leg)
    zero, ref = acc_zero_deg(leg, quiet)
    tuning = None
    if tau_s is None:
        tau_s, tuning = tune_time_constant(leg)
    return float(tau_s), FilterDiagnostics(tuning=tuning, acc_zero_deg=zero, standing_ref_deg=ref), quiet


def kf_leg(leg: LegInput, tau_s: float | None = None) -> tuple[np.ndarray, FilterDiagnostics]:
    """KF knee angle (N,) [deg] of one leg: de-biased rate, update-masked accelerometer angle less the standing
    zero, R weighted down while quiet, time constant from :func:`pipeline.tuning.tune_time_constant` unless given,
    restarted on every valid run."""
    tau, diag, quiet = filter_setup(leg, tau_s)
    rate = debiased_rate(leg)
    mask = update_mask(leg)
    scale = r_scale(leg, quiet)
    z = np.asarray(leg.acc_angle_deg, dtype=float) - diag.acc_zero_deg
    fs = leg.fs_hz
    r = leg.params.kf.r_deg2
    angle = run_per_segment(leg, lambda a, b: kf_angle(rate[a:b], z[a:b], fs, tau_s=tau, r_deg2=r,
                                                       update_mask=mask[a:b], r_scale=scale[a:b]), mask)
    return angle, diag
