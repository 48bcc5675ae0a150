"""The default ``auto`` policy: GO (Allseits et al. 2018) made ABSOLUTE per stride, with a complementary-filter
(Seel et al. 2014, Rhudy et al. 2024 Eq. 17) fallback for strides where GO's assumptions fail.

No paper does this part. GO's zero-angle update assumes the knee is straight at the minimum before swing, so a
crouch or contracture knee that never extends would read 0 deg there. Each stride's GO curve is therefore shifted by
the mean of (accelerometer angle - GO) over the quiet samples of its stance (Seel Eq. 6-7 angle).

The accelerometer angle's own zero is NOT taken from the joint-centre geometry: sensors sit a few cm anterior or
posterior of the segment axis, which tilts the sensor->knee directions by 10-30 deg (seen on the real biomechZoo trial
and in the simulator). Instead the zero is the quiet STANDING posture found in the session (both segments still,
upright: gravity along the segments as in walking stance), assumed to be STANDING_KNEE_DEG of flexion
(:func:`standing_reference`). Healthy standing is 0-6 deg, so absolute values carry that uncertainty; a crouch gait
still reads its true crouch. The per-stride offsets are smoothed with a running median over neighbouring strides (the
accelerometer angle is noisy, the true minimum flexion changes slowly) and interpolated between stride centres so the
trace is continuous. Without standing in the session the offset stays 0 (Allseits' assumption) and the stride says
so ("no_absolute_reference"). The trace is GO inside the strides that kept it, CF (shifted to the same zero)
elsewhere: fallback strides, bout edges, standing, sitting, transitions.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.estimators import LegData
from pipeline.signal_utils import row_norm, true_runs

CALM_DPS = 90.0  # both segments slower than this: accelerometer angle usable (little lever-arm acceleration)
OFFSET_SMOOTH = 11
# Relaxed quiet standing is not perfectly straight: a few degrees of flexion (healthy adults ~2-6 deg).
STANDING_KNEE_DEG = 4.0
DRIFT_MAX_DEG = 15.0
MISMATCH_DEG = 8.0
PENALTY = {"no_absolute_reference": 0.2, "no_zero_crossing": 0.3, "drift": 0.3, "saturation": 0.5,
           "go_cf_mismatch": 0.3, "cf_fallback": 0.2, "no_go_estimate": 0.3, "few_quiet_samples": 0.1,
           "bridged_gap": 0.1}


@dataclass
class StrideChoice:
    estimator: str
    quality: float
    reasons: tuple[str, ...]


@dataclass
class FusionResult:
    angle_deg: np.ndarray
    estimator: np.ndarray  # per sample
    choices: list[StrideChoice]
    info: dict = field(default_factory=dict)


def _running_median(x: np.ndarray, width: int) -> np.ndarray:
    if x.size == 0:
        return x
    half = width // 2
    padded = np.pad(x, half, mode="edge")
    return np.median(np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1), axis=1)


STAND_DPS = 15.0
STAND_MIN_S = 1.0
UPRIGHT_DEG = 45.0


def _stance_up_directions(data: LegData) -> list[np.ndarray] | None:
    """Per segment, the mean direction of the specific force (pointing up) in the joint plane over the stance phases
    of all strides: roughly the segment's proximal direction, since thigh and shank swing about the vertical in
    stance. Needs no joint-centre geometry (whose sensor->knee directions can be off by tens of degrees)."""
    strides = data.events.strides
    if not strides:
        return None
    arr = np.asarray(strides)
    lens = arr[:, 1] - arr[:, 0] + 1
    # the stance indices a..t of every stride, concatenated, without a Python loop over strides
    idx = np.repeat(arr[:, 0] - np.concatenate(([0], np.cumsum(lens)[:-1])), lens) + np.arange(int(lens.sum()))
    out = []
    for acc, j in ((data.prep.acc_thigh_mps2, data.axes.j1), (data.prep.acc_shank_mps2, data.axes.j2)):
        a = acc[idx]
        f = a - np.outer(a @ j, j)
        f /= np.maximum(row_norm(f)[:, None], 1e-9)
        m = f.mean(axis=0)
        if np.linalg.norm(m) < 0.5:  # no consistent direction: not gait-like stance
            return None
        out.append(m / np.linalg.norm(m))
    return out


def standing_reference(data: LegData, acc_angle_deg: np.ndarray, exclude: np.ndarray) -> float | None:
    """Accelerometer angle of quiet upright standing (median), or None when the session has none.

    Quiet: both segments slower than STAND_DPS for at least STAND_MIN_S, specific force within 10 % of g. Upright:
    in each joint plane the specific force is within UPRIGHT_DEG of its mean stance direction during the session's
    strides (:func:`_stance_up_directions`); sitting fails on the thigh (horizontal)."""
    prep = data.prep
    ups = _stance_up_directions(data)
    if ups is None:
        return None
    fs = prep.fs_hz
    speed = np.rad2deg(np.maximum(row_norm(prep.gyr_thigh_rps), row_norm(prep.gyr_shank_rps)))
    g = 9.80665
    still = (speed < STAND_DPS) & prep.valid & ~exclude
    for acc, up, j in ((prep.acc_thigh_mps2, ups[0], data.axes.j1), (prep.acc_shank_mps2, ups[1], data.axes.j2)):
        still &= np.abs(row_norm(acc) - g) < 0.1 * g
        y = np.cross(j, up)
        ang = np.degrees(np.arctan2(acc @ y, acc @ up))
        still &= np.abs(ang) < UPRIGHT_DEG
    min_len = int(STAND_MIN_S * fs)
    keep = np.zeros_like(still)
    for a, b in true_runs(still):
        if b - a >= min_len:
            keep[a:b] = True
    vals = acc_angle_deg[keep & np.isfinite(acc_angle_deg)]
    return float(np.median(vals)) if vals.size >= min_len else None


def _segment_sums(x: np.ndarray, starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """Sum of ``x[a:b]`` for each (non-overlapping or not) half-open range, via a prefix sum."""
    c = np.concatenate(([0.0], np.cumsum(x, dtype=float)))
    return c[stops] - c[starts]


def stance_offsets(data: LegData, go_rel: np.ndarray, strides: list[tuple[int, int, int]]
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Mean of (accelerometer angle - GO) over the quiet stance samples of each stride, and the quiet-sample count.
    Quiet: both segments' angular speed below CALM_DPS (lever-arm terms of Eq. 6 small); a stride with fewer than 5
    quiet samples uses its whole stance. The running median over strides (:func:`fuse`) removes outliers."""
    if not strides:
        return np.zeros(0), np.zeros(0, dtype=int)
    prep = data.prep
    speed = np.rad2deg(np.maximum(row_norm(prep.gyr_thigh_rps), row_norm(prep.gyr_shank_rps)))
    diff = data.acc_angle_deg - go_rel
    ok = np.isfinite(diff)
    d0 = np.where(ok, diff, 0.0)
    quiet = ok & (speed < CALM_DPS)
    arr = np.asarray(strides)
    lo, hi = arr[:, 0], arr[:, 1] + 1
    n_quiet = _segment_sums(quiet, lo, hi)
    n_ok = _segment_sums(ok, lo, hi)
    s_quiet = _segment_sums(np.where(quiet, d0, 0.0), lo, hi)
    s_ok = _segment_sums(d0, lo, hi)
    with np.errstate(invalid="ignore", divide="ignore"):
        offs = np.where(n_quiet >= 5, s_quiet / np.maximum(n_quiet, 1), s_ok / n_ok)
    offs[n_ok == 0] = np.nan
    return offs, n_quiet.astype(int)


def in_bouts(data: LegData) -> np.ndarray:
    """Samples within a second of a walking bout's first and last mid-swing (not standing)."""
    ev = data.events
    mask = np.zeros(data.prep.n, dtype=bool)
    for b in np.unique(ev.bout[ev.bout >= 0]):
        lobes = ev.ms[ev.bout == b]
        mask[max(int(lobes[0] - data.fs_hz), 0):int(lobes[-1] + data.fs_hz)] = True
    return mask


def fuse(data: LegData, go_rel: np.ndarray, go_diag: dict, cf: np.ndarray) -> FusionResult:
    """Per-sample fused angle, per-sample estimator names and one :class:`StrideChoice` per stride of
    ``data.events.strides``. Outside strides (standing, sitting, turning without strides) the CF estimate is used."""
    strides = data.events.strides
    n = go_rel.shape[0]
    ref = standing_reference(data, data.acc_angle_deg, in_bouts(data))
    absolute_ok = ref is not None
    # acc - ref reads 0 when standing; standing itself is STANDING_KNEE_DEG of flexion
    ref_deg = ref - STANDING_KNEE_DEG if ref is not None else 0.0
    offs, quiet_counts = stance_offsets(data, go_rel + ref_deg, strides)
    finite = np.isfinite(offs)
    raw_level = float(np.median(offs[finite])) if finite.any() else 0.0
    if absolute_ok and finite.any():
        filled = np.where(finite, offs, raw_level)
        smooth = _running_median(filled, OFFSET_SMOOTH)
        cf_shift = -ref_deg
    else:
        smooth = np.zeros(len(strides))
        # keep CF consistent with GO's zero when there is no absolute reference
        cf_shift = -raw_level - ref_deg
    cf_used = cf + cf_shift
    angle = cf_used.copy()
    labels = np.where(np.isfinite(angle), "cf", "")
    zi, zf, drift = go_diag["zau_idx"], go_diag["zau_found"], go_diag["drift_deg"]
    centres = np.array([(a + b) / 2.0 for a, _, b in strides])
    offset_t = np.interp(np.arange(n), centres, smooth) if len(strides) else np.zeros(n)
    go_abs = go_rel + offset_t
    choices: list[StrideChoice] = []
    if not strides:
        return FusionResult(angle_deg=angle, estimator=labels.astype(str), choices=choices,
                            info={"absolute_reference": bool(absolute_ok), "cf_shift_deg": round(cf_shift, 2)})
    arr = np.asarray(strides)
    lo, hi = arr[:, 0], arr[:, 2] + 1
    # per-stride checks from prefix sums (no per-sample Python work)
    go_ok = np.isfinite(go_abs)
    n_len = hi - lo
    go_complete = _segment_sums(go_ok, lo, hi) == n_len
    saturated = _segment_sums(data.prep.saturated, lo, hi) > 0
    bridged = np.zeros(n_len.size, dtype=bool)
    for g0, g1 in data.prep.bridged_s:
        i0, i1 = np.searchsorted(data.prep.t_s, [g0, g1])
        bridged |= (lo <= i1) & (hi > i0)
    zl, zh = np.searchsorted(zi, lo), np.searchsorted(zi, hi)
    missing = np.concatenate(([0], np.cumsum(~zf)))
    no_crossing = (missing[zh] - missing[zl]) > 0
    big_drift = np.concatenate(([0], np.cumsum(np.nan_to_num(np.abs(drift)) > DRIFT_MAX_DEG))) if drift.size \
        else np.zeros(1, dtype=int)
    d_lo, d_hi = np.clip(zl - 1, 0, drift.size), np.clip(zh, 0, drift.size)
    drifted = (big_drift[d_hi] - big_drift[d_lo]) > 0
    e = go_abs - cf_used
    e_ok = np.isfinite(e)
    e0 = np.where(e_ok, e, 0.0)
    ne = np.maximum(_segment_sums(e_ok, lo, hi), 1)
    mean_e = _segment_sums(e0, lo, hi) / ne
    var_e = np.maximum(_segment_sums(e0 * e0, lo, hi) / ne - mean_e ** 2, 0.0)
    mismatch = np.sqrt(var_e) > MISMATCH_DEG
    for k in range(len(strides)):
        reasons: list[str] = []
        if not absolute_ok:
            reasons.append("no_absolute_reference")
        elif quiet_counts[k] < 5:
            reasons.append("few_quiet_samples")
        use_go = True
        for flag, reason in ((not go_complete[k], "no_go_estimate"), (no_crossing[k], "no_zero_crossing"),
                             (drifted[k], "drift"), (saturated[k], "saturation")):
            if flag:
                reasons.append(reason)
                use_go = False
        if bridged[k]:
            reasons.append("bridged_gap")
        if use_go and mismatch[k]:
            reasons.append("go_cf_mismatch")
        if not use_go:
            reasons.append("cf_fallback")
        quality = max(0.0, 1.0 - sum(PENALTY.get(r, 0.1) for r in reasons))
        choices.append(StrideChoice(estimator="go" if use_go else "cf", quality=round(quality, 3),
                                    reasons=tuple(reasons)))
    use = np.array([c.estimator == "go" for c in choices])
    cover = np.zeros(n + 1, dtype=int)
    np.add.at(cover, lo[use], 1)
    np.add.at(cover, hi[use], -1)
    # GO inside the strides that kept it; extending it to the bout edges (gait initiation and termination, where
    # its drift line is extrapolated) was worse on the simulator (crouch) and mixed on the real trial
    go_mask = np.cumsum(cover)[:-1] > 0
    angle[go_mask] = go_abs[go_mask]
    labels = np.where(go_mask, "go", labels)
    labels = np.where(np.isfinite(angle), labels, "")
    info = {"absolute_reference": bool(absolute_ok), "standing_ref_deg": None if ref is None else round(ref, 2),
            "cf_shift_deg": round(cf_shift, 2),
            "offset_median_deg": round(raw_level, 2)}
    return FusionResult(angle_deg=angle, estimator=labels.astype(str), choices=choices, info=info)
