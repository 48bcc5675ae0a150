"""Linear Kalman filter for the knee flexion angle (Rhudy et al. 2024, Sect. 2.3.1 and 2.4.1, Eq. 9-12, 18-21).

State ``x = alpha`` (knee flexion), input ``u = g1.j1 - g2.j2`` (relative angular rate about the joint axis),
measurement ``z = alpha_acc`` (the accelerometer angle of Seel et al. 2014, Rhudy Eq. 7). Eq. 20-21:
``x_k = x_{k-1} + dt * u_{k-1}``, ``F = 1``, ``G = dt``, ``H = 1``. Scalar ``Q`` (gyroscope uncertainty) and ``R``
(accelerometer-angle uncertainty); only their ratio shapes the estimate, so the tuning knob is the steady-state
fusion time constant ``tau_s`` (:func:`q_for_time_constant` maps it to Q).

Rhudy et al. skip the measurement update +-5 % of the gait cycle around each foot strike (``update_mask``).

The registered ``kf`` (:func:`kf_leg`) adds what the paper got from Vicon: no per-dataset tuning
(:mod:`pipeline.tuning`), no motion-capture initialisation (the state starts at the first usable accelerometer
angle carried back with the gyroscope, and R shrinks 100-fold while the leg is quiet, so standing anchors the
level), the accelerometer angle's zero from quiet upright standing, and the gyro bias removed per stride (gait is
periodic: a stride's rate integrates to ~0).

Vectorised: the covariance recursion does not depend on the data, so the gain sequence is computed in closed form
per run of updates (a Moebius map with two fixed points), and the state recursion ``x_k = a_k x_{k-1} + b_k`` is
solved by cumulative products in blocks (:func:`linear_recursion`). :func:`kf_angle_loop` is the literal
Eq. 10-12 loop, kept as the reference the tests compare against.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from pipeline.estimators import LegData, register
from pipeline.prepare import G_MPS2, PreparedLeg
from pipeline.signal_utils import true_runs

# Default for the bare filter functions (the registered estimator tunes its own): a fusion time constant of 2 s is
# long against a stride (~0.7 s running, ~1.1 s walking), so the within-stride accelerometer-angle errors (impacts,
# segment accelerations: 23-32 deg RMSE in running, Rhudy Table 2) average out over several strides, and short
# against the drift of an integrated MEMS gyro. Only Q/R shapes the estimate; R = (10 deg)^2 only sets the scale of
# the initial variance.
DEFAULT_R_DEG2 = 100.0
DEFAULT_TAU_S = 2.0


def gain_for_time_constant(tau_s: float, fs_hz: float) -> float:
    """Steady-state gain of a first-order discrete low-pass with time constant ``tau_s``."""
    return float(1.0 - math.exp(-1.0 / (fs_hz * tau_s)))


def q_for_time_constant(tau_s: float, fs_hz: float, r: float = DEFAULT_R_DEG2) -> float:
    """Per-sample process noise Q (Eq. 10) whose steady-state KF has fusion time constant ``tau_s``.

    At steady state the predicted variance solves ``P^2 - Q P - Q R = 0`` and ``K = P / (P + R)``, hence
    ``Q = R K^2 / (1 - K)``. Parametrising by ``tau_s`` keeps the filter's behaviour independent of the sampling
    rate (the paper's Q at R = 1, Fig. 10, is tied to its 400 Hz)."""
    k = gain_for_time_constant(tau_s, fs_hz)
    return r * k * k / (1.0 - k)


def time_constant_for_q(q: float, fs_hz: float, r: float = DEFAULT_R_DEG2) -> float:
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


def _start_from_measurement(z: np.ndarray, mask: np.ndarray, rate_dps: np.ndarray, dt: float) -> float:
    """Initial state from the first usable accelerometer angle, carried back to sample 0 with the gyroscope."""
    first = np.flatnonzero(mask)
    if not first.size:
        return 0.0
    f = int(first[0])
    return float(z[f] - dt * np.sum(interval_rate(rate_dps)[:f]))


def kf_angle(rate_dps: np.ndarray, acc_angle_deg: np.ndarray, fs_hz: float, *,
             tau_s: float = DEFAULT_TAU_S, r_deg2: float = DEFAULT_R_DEG2,
             update_mask: np.ndarray | None = None, x0_deg: float | None = None,
             p0_deg2: float | None = None, r_scale: np.ndarray | None = None) -> np.ndarray:
    """Knee flexion (deg) by the KF of Rhudy et al. Eq. 18-21.

    ``rate_dps``: relative angular rate about the joint axis (``g1.j1 - g2.j2``), ``acc_angle_deg``: the
    accelerometer angle (Eq. 7), ``update_mask``: where the accelerometer angle may update the state (False around
    foot strikes and where it is NaN). Initialisation needs no motion capture: ``x0_deg`` (e.g. the angle of a
    standing period) with variance ``p0_deg2``; without it the filter starts from the first usable accelerometer
    angle with variance R. ``r_scale`` (per sample, default 1) multiplies R: the accelerometer angle is far more
    trustworthy while the leg is still (no segment accelerations) than in motion; Q stays set by ``tau_s``."""
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
        x0_deg, p0_deg2 = _start_from_measurement(z, mask, rate, dt), r
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
                  tau_s: float = DEFAULT_TAU_S, r_deg2: float = DEFAULT_R_DEG2,
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
        x0_deg, p0_deg2 = _start_from_measurement(z, mask, rate, dt), r
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


# ---------------------------------------------------------------------------------------------------------------
# The registered estimator: one prepared leg in, knee flexion out.

def stride_bias_dps(rate_dps: np.ndarray, strides: list[tuple[int, int]], smooth: int = 15) -> np.ndarray | None:
    """Gyroscope bias of the knee rate per sample, from the periodicity of gait: over one stride the knee returns to
    its starting angle, so ``integral(rate) / duration`` of a stride is the bias (plus the small stride-to-stride
    change of the angle). Strides far from the session median (gait initiation and termination, where the knee does
    change its angle over the stride) are dropped; the rest are smoothed by a running median over ``smooth`` strides
    and interpolated, held constant beyond the first and last. None without strides.

    The KF's random-walk model assumes zero-mean gyro errors; a bias would otherwise leave a steady offset of
    ``bias * tau`` (several degrees at 1 deg/s)."""
    vals, centres = [], []
    for a, b in strides:
        r = rate_dps[a:b + 1]
        if b - a < 2 or not np.isfinite(r).all():
            continue
        vals.append(float(np.trapezoid(r) / (b - a)))
        centres.append(0.5 * (a + b))
    if not vals:
        return None
    v, c = np.asarray(vals), np.asarray(centres)
    med = float(np.median(v))
    spread = max(3.0 * 1.4826 * float(np.median(np.abs(v - med))), 1.0)
    keep = np.abs(v - med) <= spread
    v, c = v[keep], c[keep]
    half = smooth // 2
    padded = np.pad(v, half, constant_values=np.nan)
    sm = np.nanmedian(np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1), axis=1)
    return np.interp(np.arange(rate_dps.shape[0]), c, sm)


QUIET_DPS = 15.0
QUIET_MIN_S = 0.5
QUIET_R_SCALE = 0.01


def _norm(x: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("ij,ij->i", x, x))


def quiet_mask(prep: PreparedLeg) -> np.ndarray:
    """Samples where both segments are still (slower than QUIET_DPS, specific force within 10 % of g) for at least
    QUIET_MIN_S: there the accelerometer angle sees gravity only and is accurate to a degree or two."""
    lim = math.radians(QUIET_DPS) ** 2
    still = prep.valid & (np.einsum("ij,ij->i", prep.gyr_thigh_rps, prep.gyr_thigh_rps) < lim)
    still &= np.einsum("ij,ij->i", prep.gyr_shank_rps, prep.gyr_shank_rps) < lim
    for acc in (prep.acc_thigh_mps2, prep.acc_shank_mps2):
        still &= np.abs(_norm(acc) - G_MPS2) < 0.1 * G_MPS2
    out = np.zeros(prep.n, dtype=bool)
    for a, b in true_runs(still):
        if b - a >= QUIET_MIN_S * prep.fs_hz:
            out[a:b] = True
    return out


def leg_quiet(data: LegData) -> np.ndarray:
    """:func:`quiet_mask` of the leg, computed once per leg (the KF, the EKF and the standing zero share it)."""
    if "quiet_mask" not in data.extras:
        data.extras["quiet_mask"] = quiet_mask(data.prep)
    return data.extras["quiet_mask"]


def leg_update_mask(data: LegData) -> np.ndarray:
    """Where the accelerometer may update the filters: valid samples with a finite accelerometer angle, restricted
    by ``extras["acc_update_mask"]`` when :mod:`pipeline.running` set one (running: 40-80 % of each cycle and quiet
    periods)."""
    mask = data.prep.valid & np.isfinite(data.acc_angle_deg)
    extra = data.extras.get("acc_update_mask")
    return mask & np.asarray(extra, dtype=bool) if extra is not None else mask


def leg_strides(data: LegData) -> list[tuple[int, int]]:
    """Stride intervals: running's foot-strike cycles when present, else the gait-event strides."""
    cycles = data.extras.get("running_cycles")
    if cycles:
        return [(int(a), int(b)) for a, b in cycles]
    return [(a, b) for a, _, b in data.events.strides]


UPRIGHT_DEG = 45.0  # sitting puts the thigh ~90 deg off; running leaves the shank ~30 deg off on average


def gait_gravity_directions(data: LegData) -> tuple[np.ndarray, np.ndarray] | None:
    """Unit vectors of the mean specific force in the thigh and shank frames over the strides: during gait both
    segments swing about the vertical, so these are close to each segment's long axis (pointing up)."""
    strides = leg_strides(data)
    if not strides:
        return None
    sel = np.zeros(data.prep.n, dtype=bool)
    for a, b in strides:
        sel[a:b] = True
    sel &= data.prep.valid
    out = []
    for acc in (data.prep.acc_thigh_mps2, data.prep.acc_shank_mps2):
        m = acc[sel].mean(axis=0)
        norm = float(np.linalg.norm(m))
        if norm < 0.5 * G_MPS2:
            return None
        out.append(m / norm)
    return out[0], out[1]


def standing_mask(data: LegData) -> np.ndarray:
    """Quiet samples (:func:`quiet_mask`) with both segments upright: the specific force within UPRIGHT_DEG of its
    mean direction during gait. Tells standing from sitting and lying without the joint-centre geometry."""
    quiet = leg_quiet(data).copy()
    dirs = gait_gravity_directions(data)
    if dirs is None or not quiet.any():
        return np.zeros_like(quiet)
    cos_lim = math.cos(math.radians(UPRIGHT_DEG))
    for acc, u in zip((data.prep.acc_thigh_mps2, data.prep.acc_shank_mps2), dirs, strict=True):
        norm = np.maximum(_norm(acc), 1e-9)
        quiet &= (acc @ u) / norm > cos_lim
    return quiet


def acc_zero_deg(data: LegData) -> float:
    """Accelerometer-angle reading of a straight knee: the median accelerometer angle of quiet upright standing
    minus the standing knee flexion the ``auto`` policy assumes (:data:`pipeline.fusion.STANDING_KNEE_DEG`). The
    joint-centre geometry alone leaves a 10-40 deg offset. 0 without standing (the angle is taken as it is)."""
    from pipeline.fusion import STANDING_KNEE_DEG

    stand = standing_mask(data) & np.isfinite(data.acc_angle_deg)
    if stand.sum() < data.fs_hz:
        return 0.0
    return float(np.median(data.acc_angle_deg[stand]) - STANDING_KNEE_DEG)


def debiased_rate(data: LegData) -> np.ndarray:
    rate = np.asarray(data.rate_dps, dtype=float)
    bias = stride_bias_dps(rate, leg_strides(data))
    return rate if bias is None else rate - bias


def run_per_segment(data: LegData, fn: Callable[[int, int], np.ndarray]) -> np.ndarray:
    """``fn(a, b)`` on each valid run ``[a, b)`` of the leg (the filters restart after a masked gap), NaN elsewhere."""
    ok = data.prep.valid & np.isfinite(data.rate_dps)
    out = np.full(ok.shape[0], np.nan)
    for a, b in true_runs(ok):
        if b - a >= 2:
            out[a:b] = fn(a, b)
    return out


def kf_leg(data: LegData, tau_s: float | None = None) -> np.ndarray:
    """KF knee angle of one leg: de-biased rate, impact-masked accelerometer angle, time constant from
    :func:`pipeline.tuning.tune_time_constant` unless given, restarted on every valid run."""
    from pipeline.tuning import tune_time_constant

    rate = debiased_rate(data)
    mask = leg_update_mask(data)
    r_scale = np.where(leg_quiet(data), QUIET_R_SCALE, 1.0)
    zero = acc_zero_deg(data)
    z = np.asarray(data.acc_angle_deg, dtype=float) - zero
    fs = data.fs_hz

    def run(t: float) -> np.ndarray:
        return run_per_segment(data, lambda a, b: kf_angle(rate[a:b], z[a:b], fs, tau_s=t, update_mask=mask[a:b],
                                                           r_scale=r_scale[a:b]))

    if tau_s is None:
        tau_s, diag = tune_time_constant(data)
        data.extras["kf_tuning"] = {**diag, "acc_zero_deg": round(zero, 2)}
    return run(float(tau_s))


def cf_running_leg(data: LegData, tau_s: float | None = None) -> np.ndarray:
    """The complementary filter of Eq. 17 (constant gain ``lambda = dt / tau``) on a running leg, with the same
    inputs as the KF (de-biased rate, standing zero, measurement updates only where ``leg_update_mask`` allows:
    Rhudy et al. skip the impacts for CF, KF and EKF alike) and the same time constant, so the two differ only in
    the gain schedule."""
    from pipeline.tuning import tune_time_constant

    rate = interval_rate(debiased_rate(data))
    mask = leg_update_mask(data)
    z = np.asarray(data.acc_angle_deg, dtype=float) - acc_zero_deg(data)
    fs = data.fs_hz
    if tau_s is None:
        tau_s, _ = tune_time_constant(data)
    lam = gain_for_time_constant(float(tau_s), fs)

    def run(a: int, b: int) -> np.ndarray:
        gains = np.where(mask[a:b], lam, 0.0)
        drive = np.concatenate(([0.0], rate[a:b - 1] / fs))
        x0 = _start_from_measurement(z[a:b], mask[a:b], rate[a:b], 1.0 / fs)
        return linear_recursion(1.0 - gains, (1.0 - gains) * drive + gains * np.where(mask[a:b], z[a:b], 0.0), x0)

    return run_per_segment(data, run)


@register("kf")
def kf_estimator(data: LegData) -> np.ndarray:
    return kf_leg(data)
