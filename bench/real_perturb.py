"""Perturbation and invariance benchmark on the REAL biomechZoo recording (Xsens thighs/shanks + Vicon knee angles).

Each perturbation is applied to the real sensor data of ``../shared/data/real`` (:mod:`bench.real_data`); the
pipeline's output (:func:`pipeline.session.process_session`) is compared per leg with the unperturbed run and with
the Vicon reference. Nothing is fitted to the reference: the perturbations are physics, not tuning.

Groups:

* ``invariant``: the knee angle does not depend on them, so the output should not move: a random rotation of each
  sensor's frame (any mounting), a signed axis permutation, the mirror image of the whole recording (acc -> Q acc,
  gyro -> -Q gyro for an improper Q: what right-handed sensors on the mirrored walker read), a common time shift of
  all sensors, the order and IDs of the sensors in the upload.
* ``tolerated``: small, bounded change expected: resampling, gyro/accelerometer bias, gain error, added white noise,
  a thigh-shank clock offset, bursty packet loss, the trial tiled into a longer session.
* ``labels``: wrong sensor labels; they should be detected and corrected, or refused with a warning.
* ``diagnostic``: not a physical motion (a left-handed relabelling of the axes); shown for information.

The single-sensor perturbations are applied to the Tan et al. right-shank step windows too (heel strike and
toe-off against the force plate).

Per perturbation, estimator and leg: strides found (min-max over repetitions), matched strides' swing-peak and ROM
change vs the unperturbed run and the RMS change of the continuous trace (max over repetitions), the zero-mean RMSE
and mean abs swing-peak error vs Vicon as :func:`bench.accuracy.real_tables` computes them (worst repetition), the
samples masked as implausible and any stored angle outside [-15, 160] deg, and the session's warnings.

    python -m bench.real_perturb               # all perturbations, auto + every estimator (~40 s on one core)
    python -m bench.real_perturb --quick       # 2 repetitions, auto only (smoke run)
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import resample_poly
from scipy.spatial.transform import Rotation

from pipeline.constants import G_MPS2
from pipeline.params import WALKING
from pipeline.session import process_session
from pipeline.simulate import gilbert_elliott_losses
from pipeline.types import RawSensorStream, SessionResult

BAND_DEG = WALKING.posture.plausible_knee_deg
ESTIMATORS = ("auto", "go", "cf", "kf", "ekf")
LEGS = ("left", "right")
# a perturbed stride is the same stride as an unperturbed one when their heel strikes are this close
MATCH_S = 0.15
# a lost stride is "keepable" when no hole longer than the bridge limit comes this close to it: its heel strikes
# are found on low-passed rates after the preceding mid-swing peak, so a hole just outside the stride hides them too
KEEP_MARGIN_S = 0.25
# what trends take (server.trends.metrics.MIN_QUALITY; bench does not import the server for one number)
TREND_QUALITY = 0.5
# an invariant perturbation "moves" the output above this (the brief's ~1 deg); the tolerated bound is wider
INVARIANT_DEG = 1.0
TOLERATED_DEG = 3.0
# Gilbert-Elliott mean burst length [packets], as the simulator's robustness sweep uses for its loss axis
BURST_PACKETS = 4.0
PACKET_SAMPLES = 20


@dataclass
class Applied:
    """A perturbed upload. ``t_shift_s``: added to every time stamp (subtract to compare); ``holes_s``: the lost
    intervals (packet loss)."""

    streams: list[RawSensorStream]
    t_shift_s: float = 0.0
    holes_s: list[tuple[float, float]] = field(default_factory=list)
    tiled: tuple[float, float, int] | None = None  # (cut start, cut end, copies) of a tiled session


Perturb = Callable[[list[RawSensorStream], np.random.Generator], Applied]


@dataclass(frozen=True)
class Perturbation:
    name: str
    group: str
    reps: int
    apply: Perturb


def _replace(s: RawSensorStream, **kw) -> RawSensorStream:
    return dataclasses.replace(s, **kw)


def _si(s: RawSensorStream) -> tuple[np.ndarray, np.ndarray]:
    gyr = np.asarray(s.gyr, float) * (np.pi / 180.0 if s.gyro_unit == "deg/s" else 1.0)
    acc = np.asarray(s.acc, float) * (G_MPS2 if s.acc_unit == "g" else 1.0)
    return gyr, acc


def _with_si(s: RawSensorStream, gyr_rps: np.ndarray, acc_mps2: np.ndarray, **kw) -> RawSensorStream:
    return _replace(s, gyr=gyr_rps, acc=acc_mps2, gyro_unit="rad/s", acc_unit="m/s2", **kw)


# --- invariant -------------------------------------------------------------------------------------------------


def rotate(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
    """Each sensor's frame turned by its own uniformly random rotation (another mounting of the same sensor)."""
    out = []
    for s in streams:
        r = Rotation.random(random_state=rng).as_matrix()
        gyr, acc = _si(s)
        out.append(_with_si(s, gyr @ r.T, acc @ r.T))
    return Applied(out)


def _signed_permutation(rng: np.random.Generator, det: float) -> np.ndarray:
    while True:
        p = np.eye(3)[rng.permutation(3)] * rng.choice([-1.0, 1.0], size=3)[:, None]
        if np.sign(np.linalg.det(p)) == det:
            return p


def permute_axes(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
    """Each sensor's axes relabelled by a random signed permutation with det +1 (a 90-degree mounting change; the
    knee axis may fall exactly on a sensor axis)."""
    out = []
    for s in streams:
        p = _signed_permutation(rng, 1.0)
        gyr, acc = _si(s)
        out.append(_with_si(s, gyr @ p.T, acc @ p.T))
    return Applied(out)


def mirror(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
    """The mirror image of the recording: right-handed sensors on the mirrored walker read acc -> Q acc and, the
    angular rate being an axial vector, gyro -> det(Q) Q gyro = -Q gyro, for an improper Q (a reflection times a
    random rotation per sensor). The mirrored knee flexes exactly as the real one."""
    out = []
    for s in streams:
        q = Rotation.random(random_state=rng).as_matrix() @ np.diag([-1.0, 1.0, 1.0])
        gyr, acc = _si(s)
        out.append(_with_si(s, -(gyr @ q.T), acc @ q.T))
    return Applied(out)


def left_handed(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
    """A left-handed relabelling of each sensor's axes (acc and gyro both -> P x, det P = -1): not a motion any
    right-handed sensor can record (a driver convention error); diagnostic only."""
    out = []
    for s in streams:
        p = _signed_permutation(rng, -1.0)
        gyr, acc = _si(s)
        out.append(_with_si(s, gyr @ p.T, acc @ p.T))
    return Applied(out)


def time_shift(shift_s: float) -> Perturb:
    def f(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
        return Applied([_replace(s, t_s=np.asarray(s.t_s, float) + shift_s) for s in streams], t_shift_s=shift_s)
    return f


def shuffle_sensors(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
    """The streams uploaded in another order and under other sensor IDs."""
    order = rng.permutation(len(streams))
    return Applied([_replace(streams[i], sensor_id=f"imu-{rng.integers(1 << 30):08x}") for i in order])


# --- tolerated -------------------------------------------------------------------------------------------------


def resample(fs_hz: float) -> Perturb:
    """The streams at another rate: polyphase resampling with its anti-alias FIR (scipy ``resample_poly``, Kaiser
    window), as a sensor sampling at that rate behind its own anti-alias filter would deliver."""
    def f(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
        out = []
        for s in streams:
            fs0 = float(s.fs_hz)
            frac = (fs_hz / fs0)
            up, down = _ratio(frac)
            gyr, acc = _si(s)
            g2 = resample_poly(gyr, up, down, axis=0, padtype="line")
            a2 = resample_poly(acc, up, down, axis=0, padtype="line")
            t2 = float(s.t_s[0]) + np.arange(g2.shape[0]) / fs_hz
            out.append(_with_si(s, g2, a2, t_s=t2, fs_hz=fs_hz))
        return Applied(out)
    return f


def _ratio(x: float) -> tuple[int, int]:
    from fractions import Fraction
    fr = Fraction(x).limit_denominator(1000)
    return fr.numerator, fr.denominator


def gyro_bias(dps: float) -> Perturb:
    """A constant gyro bias of ``dps`` in a random direction per sensor."""
    def f(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
        out = []
        for s in streams:
            gyr, acc = _si(s)
            out.append(_with_si(s, gyr + np.deg2rad(dps) * _unit(rng), acc))
        return Applied(out)
    return f


def acc_bias(g: float) -> Perturb:
    """A constant accelerometer bias of ``g`` in a random direction per sensor."""
    def f(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
        out = []
        for s in streams:
            gyr, acc = _si(s)
            out.append(_with_si(s, gyr, acc + g * G_MPS2 * _unit(rng)))
        return Applied(out)
    return f


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def gain(pct: float) -> Perturb:
    """Per axis of gyro and accelerometer, a scale error of +-``pct`` % (random sign per axis and sensor)."""
    def f(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
        out = []
        for s in streams:
            gyr, acc = _si(s)
            out.append(_with_si(s, gyr * (1 + pct / 100 * rng.choice([-1.0, 1.0], 3)),
                                acc * (1 + pct / 100 * rng.choice([-1.0, 1.0], 3))))
        return Applied(out)
    return f


def native_noise_sd(x: np.ndarray) -> np.ndarray:
    """Per channel, the white-noise floor of a recorded signal: the median absolute second difference / 0.6745 /
    sqrt(6) (a white sequence's second difference has variance 6 sd^2; the median keeps the gait's own curvature,
    concentrated in few samples, out). An upper bound: any high-frequency motion counts as noise."""
    d2 = np.diff(x, n=2, axis=0)
    return np.median(np.abs(d2), axis=0) / 0.6745 / math.sqrt(6.0)


def noise(factor: float) -> Perturb:
    """White noise added so that the noise floor (:func:`native_noise_sd`) grows ``factor``-fold."""
    def f(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
        out = []
        k = math.sqrt(factor**2 - 1.0)
        for s in streams:
            gyr, acc = _si(s)
            out.append(_with_si(s, gyr + rng.normal(size=gyr.shape) * k * native_noise_sd(gyr),
                                acc + rng.normal(size=acc.shape) * k * native_noise_sd(acc)))
        return Applied(out)
    return f


def clock_offset(ms: float) -> Perturb:
    """Each shank's time stamps shifted by +-``ms`` (random sign per leg) against its thigh."""
    def f(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
        sign = {leg: rng.choice([-1.0, 1.0]) for leg in LEGS}
        return Applied([_replace(s, t_s=np.asarray(s.t_s, float) + sign[s.leg] * ms / 1000.0)
                        if s.segment == "shank" else s for s in streams])
    return f


def packet_loss(loss: float) -> Perturb:
    """Bursty loss of 20-sample packets per sensor, independently (Gilbert-Elliott, mean burst 4 packets, as
    :mod:`bench.robustness`); the first packet always arrives."""
    def f(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
        out, holes = [], []
        for s in streams:
            n = np.asarray(s.t_s).size
            n_packets = -(-n // PACKET_SAMPLES)
            lost = gilbert_elliott_losses(rng, n_packets, loss, BURST_PACKETS)
            lost[0] = False
            keep = ~np.repeat(lost, PACKET_SAMPLES)[:n]
            t = np.asarray(s.t_s, float)
            gyr, acc = _si(s)
            out.append(_with_si(s, gyr[keep], acc[keep], t_s=t[keep]))
            idx = np.flatnonzero(np.diff(np.concatenate(([0], (~keep).astype(int), [0]))))
            for a, b in zip(idx[::2], idx[1::2], strict=True):
                holes.append((float(t[max(a - 1, 0)]), float(t[min(b, n - 1)])))
        return Applied(out, holes_s=holes)
    return f


def tile(copies: int) -> Perturb:
    """The trial's steady part repeated ``copies`` times: cut between two right-shank mid-swing peaks at which the
    left shank is at the same phase too (nearest equal lag to its own mid-swing), so each seam joins the same gait
    phase of the same walker; 10 samples are cross-faded. The sensors' heading does not enter their readings;
    what changes at a seam is only the stride-to-stride variability. Vicon is tiled the same way."""
    def f(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
        a, b = _tile_cut(streams)
        out = []
        for s in streams:
            gyr, acc = _si(s)
            t = np.asarray(s.t_s, float)
            i0, i1 = np.searchsorted(t, a), np.searchsorted(t, b)
            gyr2, acc2 = _tile_block(gyr, i0, i1, copies), _tile_block(acc, i0, i1, copies)
            t2 = t[0] + np.arange(gyr2.shape[0]) / float(s.fs_hz)
            out.append(_with_si(s, gyr2, acc2, t_s=t2))
        return Applied(out, tiled=(a, b, copies))
    return f


_FADE = 10


def _tile_block(x: np.ndarray, i0: int, i1: int, copies: int) -> np.ndarray:
    """``x`` with its samples ``i0:i1`` repeated ``copies`` times. At each seam between two copies the samples
    blend, over ``_FADE`` samples, from the original continuation past ``i1`` into the next copy's start."""
    seg = x[i0:i1]
    y = np.concatenate([x[:i0], *([seg] * copies), x[i1:]])
    h = _FADE // 2
    w = np.linspace(0.0, 1.0, 2 * h)[:, None]
    natural = x[i1 - h:i1 + h]
    for k in range(1, copies):
        lo = i0 + k * (i1 - i0) - h
        if natural.shape[0] == 2 * h and lo >= 0:
            y[lo:lo + 2 * h] = (1 - w) * natural + w * y[lo:lo + 2 * h]
    return y


def _tile_cut(streams: list[RawSensorStream]) -> tuple[float, float]:
    """Cut times [s] for :func:`tile`: right-shank mid-swing peaks (largest principal-axis rate lobes) nearest to
    2 s and to the end minus 2 s, moved so that the left shank's phase matches."""
    by = {(s.leg, s.segment): s for s in streams}
    sh_r, sh_l = by[("right", "shank")], by[("left", "shank")]
    t = np.asarray(sh_r.t_s, float)
    pk_r = _swing_peaks(sh_r)
    pk_l = _swing_peaks(sh_l)
    pairs = []
    for i in pk_r:
        for j in pk_r:
            if t[j] - t[i] < 4.0:
                continue
            lag_i = _lag_to_next(t, t[i], pk_l)
            lag_j = _lag_to_next(t, t[j], pk_l)
            pairs.append((abs(lag_i - lag_j), -(t[j] - t[i]), t[i], t[j]))
    if not pairs:
        raise ValueError("no matching cut for tiling")
    pairs.sort()
    return pairs[0][2], pairs[0][3]


def _lag_to_next(t: np.ndarray, t0: float, peaks: np.ndarray) -> float:
    nxt = t[peaks][t[peaks] > t0]
    return float(nxt[0] - t0) if nxt.size else math.inf


def _swing_peaks(s: RawSensorStream) -> np.ndarray:
    from scipy.signal import find_peaks
    gyr, _ = _si(s)
    c = gyr - gyr.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    w = c @ vt[0]
    if np.abs(w.min()) > np.abs(w.max()):
        w = -w
    pk, _ = find_peaks(w, height=0.5 * np.max(w), distance=int(0.6 * float(s.fs_hz)))
    # skip the first and last stride: bout edges are not the steady phase a seam should join
    return pk[1:-1]


# --- labels ----------------------------------------------------------------------------------------------------


def swap_segments(legs: Sequence[str]) -> Perturb:
    """Thigh and shank labels exchanged on ``legs``."""
    def f(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
        other = {"thigh": "shank", "shank": "thigh"}
        return Applied([_replace(s, segment=other[s.segment]) if s.leg in legs else s for s in streams])
    return f


def swap_legs(segments: Sequence[str]) -> Perturb:
    """Left and right labels exchanged on the ``segments`` sensors."""
    def f(streams: list[RawSensorStream], rng: np.random.Generator) -> Applied:
        other = {"left": "right", "right": "left"}
        return Applied([_replace(s, leg=other[s.leg]) if s.segment in segments else s for s in streams])
    return f


def perturbations() -> list[Perturbation]:
    p = Perturbation
    out = [
        p("random rotation of every sensor frame", "invariant", 8, rotate),
        p("signed axis permutation per sensor (det +1)", "invariant", 6, permute_axes),
        p("mirror image (acc Q, gyro -Q, Q improper)", "invariant", 6, mirror),
        p("common time shift +4 ms (sub-sample)", "invariant", 1, time_shift(0.004)),
        p("common time shift +1.37 s", "invariant", 1, time_shift(1.37)),
        p("common time shift +3600 s", "invariant", 1, time_shift(3600.0)),
        p("sensor order and IDs permuted", "invariant", 4, shuffle_sensors),
    ]
    out += [p(f"resampled to {fs:g} Hz", "tolerated", 1, resample(fs)) for fs in (40.0, 50.0, 60.0, 128.0, 200.0)]
    out += [p(f"gyro bias {b:g} deg/s", "tolerated", 4, gyro_bias(b)) for b in (0.5, 1.0, 2.0)]
    out += [p(f"accelerometer bias {b:g} g", "tolerated", 4, acc_bias(b)) for b in (0.03, 0.05, 0.1)]
    out += [p("gain error +-2 % per axis", "tolerated", 4, gain(2.0))]
    out += [p(f"white noise x{k:g}", "tolerated", 4, noise(k)) for k in (2.0, 3.0, 5.0)]
    out += [p(f"thigh-shank clock offset {ms:g} ms", "tolerated", 4, clock_offset(ms)) for ms in (5.0, 10.0, 20.0)]
    out += [p(f"bursty packet loss {100 * x:g} %", "tolerated", 6, packet_loss(x)) for x in (0.01, 0.03, 0.05, 0.10)]
    out += [p("tiled x3 (seams at matched phase)", "tolerated", 1, tile(3))]
    out += [
        p("thigh<->shank labels, left leg", "labels", 1, swap_segments(["left"])),
        p("thigh<->shank labels, right leg", "labels", 1, swap_segments(["right"])),
        p("thigh<->shank labels, both legs", "labels", 1, swap_segments(["left", "right"])),
        p("thighs exchanged between legs", "labels", 1, swap_legs(["thigh"])),
        p("shanks exchanged between legs", "labels", 1, swap_legs(["shank"])),
        p("left<->right labels (all four)", "labels", 1, swap_legs(["thigh", "shank"])),
        p("left-handed axis relabelling (acc P, gyro P)", "diagnostic", 4, left_handed),
    ]
    return out


# --- scoring ---------------------------------------------------------------------------------------------------


@dataclass
class LegAgg:
    """Per (perturbation, estimator, leg), accumulated over the repetitions."""

    strides: list[int] = field(default_factory=list)
    lost: int = 0  # unperturbed strides with no perturbed stride within MATCH_S
    lost_keepable: int = 0  # of those, the ones no hole longer than the periodic bridge limit touches
    extra: int = 0
    d_peak: float = 0.0
    d_peak_trend: float = 0.0  # d_peak over the perturbed strides of quality >= TREND_QUALITY
    d_rom: float = 0.0  # over the trend strides too
    d_trace: float = 0.0
    zm_rmse: float = 0.0
    peak_err: float = 0.0
    masked: int = 0
    out_of_band: int = 0

    def worst(self, name: str, value: float) -> None:
        if math.isfinite(value):
            setattr(self, name, max(getattr(self, name), value))
        else:
            setattr(self, name, math.nan)


def vicon_scores(lr, vicon: tuple[np.ndarray, np.ndarray], t_shift_s: float,
                 tiled: tuple[float, float, int] | None) -> tuple[float, float]:
    """(zero-mean RMSE over every finite sample, mean abs swing-peak error) as :func:`bench.accuracy.real_tables`."""
    t_ref, ref = vicon
    if tiled is not None:
        t_ref, ref = _tile_ref(t_ref, ref, tiled)
    t = lr.t_s - t_shift_s
    ok = np.isfinite(lr.angle_deg) & (t >= t_ref[0]) & (t <= t_ref[-1])
    if not ok.any():
        return math.nan, math.nan
    e = lr.angle_deg[ok] - np.interp(t[ok], t_ref, ref)
    zm = float(np.sqrt(np.mean((e - e.mean()) ** 2)))
    pe = []
    for s in lr.strides:
        m = (t_ref >= s.t_toe_off_s - t_shift_s) & (t_ref <= s.t_end_s - t_shift_s)
        if m.any():
            pe.append(s.peak_swing_flexion_deg - float(ref[m].max()))
    return zm, float(np.mean(np.abs(pe))) if pe else math.nan


def _tile_ref(t_ref: np.ndarray, ref: np.ndarray, tiled: tuple[float, float, int]) -> tuple[np.ndarray, np.ndarray]:
    a, b, copies = tiled
    fs = 1.0 / float(np.median(np.diff(t_ref)))
    y = _tile_block(ref[:, None], int(np.searchsorted(t_ref, a)), int(np.searchsorted(t_ref, b)), copies)[:, 0]
    return t_ref[0] + np.arange(y.size) / fs, y


def compare(agg: LegAgg, lr, base, t_shift_s: float, holes_s: list[tuple[float, float]],
            tiled: tuple[float, float, int] | None) -> None:
    """Stride and trace changes of one perturbed leg against the unperturbed one (``base``)."""
    agg.strides.append(len(lr.strides))
    starts = np.array([s.t_start_s - t_shift_s for s in lr.strides])
    base_strides = base.strides
    if tiled is not None:
        base_strides = _tiled_base(base, tiled)
    used: set[int] = set()
    limit_s = WALKING.prepare.periodic_bridge_s
    for bs in base_strides:
        k = int(np.argmin(np.abs(starts - bs.t_start_s))) if starts.size else -1
        if k < 0 or abs(starts[k] - bs.t_start_s) > MATCH_S or k in used:
            agg.lost += 1
            if not any(h1 - h0 > limit_s and h0 < bs.t_end_s + KEEP_MARGIN_S and h1 > bs.t_start_s - KEEP_MARGIN_S
                       for h0, h1 in holes_s):
                agg.lost_keepable += 1
            continue
        used.add(k)
        s = lr.strides[k]
        agg.worst("d_peak", abs(s.peak_swing_flexion_deg - bs.peak_swing_flexion_deg))
        if s.quality >= TREND_QUALITY:
            agg.worst("d_peak_trend", abs(s.peak_swing_flexion_deg - bs.peak_swing_flexion_deg))
            agg.worst("d_rom", abs(s.rom_deg - bs.rom_deg))
    agg.extra += len(lr.strides) - len(used)
    if tiled is None:
        t = lr.t_s - t_shift_s
        ok = np.isfinite(lr.angle_deg)
        if ok.sum() >= 2:
            b = np.interp(t[ok], base.t_s, base.angle_deg, left=np.nan, right=np.nan)
            fin = np.isfinite(b)
            if fin.any():
                agg.worst("d_trace", float(np.sqrt(np.mean((lr.angle_deg[ok][fin] - b[fin]) ** 2))))


@dataclass(frozen=True)
class _TiledStride:
    t_start_s: float
    t_end_s: float
    peak_swing_flexion_deg: float
    rom_deg: float


def _tiled_base(base, tiled: tuple[float, float, int]) -> list[_TiledStride]:
    """The unperturbed strides where the tiled session has them: those starting before the cut once, those
    starting inside it once per copy, those starting after it after the last copy."""
    a, b, copies = tiled
    period = b - a
    out = []
    for s in base.strides:
        shifts = [0] if s.t_start_s < a else range(copies) if s.t_start_s < b else [copies - 1]
        out += [_TiledStride(s.t_start_s + k * period, s.t_end_s + k * period, s.peak_swing_flexion_deg, s.rom_deg)
                for k in shifts]
    return out


@dataclass
class RowResult:
    pert: Perturbation
    estimator: str
    legs: dict[str, LegAgg]
    warnings: set[str]
    assignment: set[str]
    errors: list[str]
    notes: set[str] = field(default_factory=set)


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run_one(pert: Perturbation, estimator: str, streams: list[RawSensorStream],
            vicon: dict[str, tuple[np.ndarray, np.ndarray]], base: SessionResult, seed: int,
            activity: str = "walking", reps: int | None = None) -> RowResult:
    """All repetitions of one perturbation for one estimator, compared with ``base`` (the unperturbed run)."""
    row = RowResult(pert, estimator, {leg: LegAgg() for leg in LEGS}, set(), set(), [])
    # the same draws for every estimator: the estimators see the same perturbed uploads
    rng = np.random.default_rng([seed, sum(map(ord, pert.name))])
    for _ in range(reps if reps is not None else pert.reps):
        ap = pert.apply(list(streams), rng)
        try:
            res = process_session(ap.streams, activity=activity, estimator=estimator)
        except ValueError as exc:
            row.errors.append(str(exc))
            continue
        row.warnings.update(res.warnings)
        for leg in LEGS:
            agg = row.legs[leg]
            lr = res.legs.get(leg)
            if lr is None:
                agg.strides.append(0)
                agg.lost += len(base.legs[leg].strides)
                continue
            if lr.diagnostics is not None:
                row.assignment.add(lr.diagnostics.assignment)
                agg.masked = max(agg.masked, lr.diagnostics.masked_implausible_samples)
            fin = lr.angle_deg[np.isfinite(lr.angle_deg)]
            agg.out_of_band = max(agg.out_of_band, int(np.sum((fin < BAND_DEG[0]) | (fin > BAND_DEG[1]))))
            # wrong labels: the change is measured against the unperturbed leg the output is closest to (a
            # left/right exchange of all four sensors is invisible to IMUs: the mirror image is the same gait)
            ref_leg = _closest_leg(lr, base) if pert.group == "labels" else leg
            if ref_leg != leg:
                row.notes.add(f"{leg} output = {ref_leg} leg")
            compare(agg, lr, base.legs[ref_leg], ap.t_shift_s, ap.holes_s, ap.tiled)
            zm, pe = vicon_scores(lr, vicon[leg], ap.t_shift_s, ap.tiled)
            agg.worst("zm_rmse", zm)
            agg.worst("peak_err", pe)
    return row


def _closest_leg(lr, base: SessionResult) -> str:
    """The leg of the unperturbed run whose trace the output ``lr`` follows most closely (RMS)."""
    best, leg_best = math.inf, lr.leg
    for leg, b in base.legs.items():
        ok = np.isfinite(lr.angle_deg)
        d = lr.angle_deg[ok] - np.interp(lr.t_s[ok], b.t_s, b.angle_deg)
        d = d[np.isfinite(d)]
        rms = float(np.sqrt(np.mean(d**2))) if d.size else math.inf
        if rms < best:
            best, leg_best = rms, leg
    return leg_best


def _f(x: float, fmt: str = "{:.2f}") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else fmt.format(x)


def _flag(text: str, bad: bool) -> str:
    return f"{text} ✗" if bad else text


def _bound(group: str) -> float:
    return INVARIANT_DEG if group == "invariant" else TOLERATED_DEG


def _strides_cell(agg: LegAgg, n_base: int) -> str:
    lo, hi = (min(agg.strides), max(agg.strides)) if agg.strides else (0, 0)
    txt = f"{lo}" if lo == hi else f"{lo}-{hi}"
    miss = agg.lost_keepable > 0 or agg.extra > 0
    extra = []
    if agg.lost:
        extra.append(f"-{agg.lost}" + (f" ({agg.lost_keepable} keepable)" if agg.lost != agg.lost_keepable else ""))
    if agg.extra:
        extra.append(f"+{agg.extra}")
    return _flag(txt + (f" ({', '.join(extra)})" if extra else ""), miss)


def _short_warnings(ws: set[str]) -> str:
    if not ws:
        return ""
    out = []
    for w in sorted(ws):
        w = w.split(" (")[0] if len(w) > 90 else w
        out.append(w.replace("|", "/"))
    return "; ".join(sorted(set(out)))


def table_main(rows: list[RowResult], base: dict[str, SessionResult], base_scores: dict) -> list[str]:
    """One Markdown table for one estimator: per perturbation, per leg."""
    est = rows[0].estimator
    b = base[est]
    out = [f"#### `{est}`", "",
           f"Unperturbed: left {len(b.legs['left'].strides)} strides, zero-mean RMSE "
           f"{_f(base_scores[est]['left'][0])}, swing-peak err {_f(base_scores[est]['left'][1])} deg; right "
           f"{len(b.legs['right'].strides)} strides, {_f(base_scores[est]['right'][0])}, "
           f"{_f(base_scores[est]['right'][1])} deg.", "",
           "| group | perturbation | reps | strides L / R | Δpeak L / R (deg) | Δpeak, trend strides L / R (deg) "
           "| ΔROM, trend strides L / R (deg) | Δtrace RMS L / R (deg) | zero-mean RMSE vs Vicon L / R (deg) "
           "| swing-peak err L / R (deg) | masked / out of band | warnings |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        bound = _bound(r.pert.group)
        L, R = r.legs["left"], r.legs["right"]
        cells = []
        cells.append(" / ".join(_strides_cell(r.legs[leg], len(b.legs[leg].strides)) for leg in LEGS))
        for name in ("d_peak", "d_peak_trend", "d_rom", "d_trace"):
            # tolerated perturbations: the bound applies to what trends take; a stride flagged below the trend
            # threshold (its swing peak in a filled hole, say) may move more
            judged = r.pert.group == "invariant" or (r.pert.group == "tolerated" and name != "d_peak")
            cells.append(" / ".join(_flag(_f(getattr(a, name)), judged and not getattr(a, name) <= bound)
                                    for a in (L, R)))
        cells.append(" / ".join(_f(a.zm_rmse) for a in (L, R)))
        cells.append(" / ".join(_f(a.peak_err) for a in (L, R)))
        oob = L.out_of_band + R.out_of_band
        cells.append(_flag(f"{L.masked + R.masked} / {oob}", oob > 0))
        warn = _short_warnings(r.warnings)
        if r.errors:
            warn = (warn + "; " if warn else "") + "refused: " + "; ".join(sorted(set(r.errors)))
        asg = sorted(a for a in r.assignment if a != "as_labelled")
        if asg:
            warn = (warn + "; " if warn else "") + "assignment: " + ", ".join(asg)
        if r.notes:
            warn = (warn + "; " if warn else "") + "; ".join(sorted(r.notes))
        if r.pert.group == "labels" and not r.warnings and not r.errors:
            warn = (warn + "; " if warn else "") + "**not detected**"
        out.append(f"| {r.pert.group} | {r.pert.name} | {r.pert.reps} | " + " | ".join(cells) + f" | {warn} |")
    out.append("")
    return out


def table_compact(rows_by_est: dict[str, list[RowResult]]) -> list[str]:
    """Every estimator side by side: the largest swing-peak change of either leg, and the strides found."""
    ests = list(rows_by_est)
    out = ["#### All estimators: max |Δpeak| over both legs (deg), strides L / R (min over repetitions)", "",
           "✗ as above (tolerated rows: judged on the trend strides' Δpeak).", "",
           "| group | perturbation | " + " | ".join(f"`{e}`" for e in ests) + " |",
           "|---|---|" + "---|" * len(ests)]
    for i, r0 in enumerate(rows_by_est[ests[0]]):
        cells = []
        for e in ests:
            r = rows_by_est[e][i]
            d = max(r.legs["left"].d_peak, r.legs["right"].d_peak)
            d_trend = max(r.legs["left"].d_peak_trend, r.legs["right"].d_peak_trend)
            bad = (r.pert.group == "invariant" and not d <= _bound(r.pert.group)) or \
                (r.pert.group == "tolerated" and not d_trend <= _bound(r.pert.group))
            n = " / ".join(str(min(r.legs[leg].strides)) if r.legs[leg].strides else "0" for leg in LEGS)
            cells.append(_flag(f"{_f(d)} ({n})", bad))
        out.append(f"| {r0.pert.group} | {r0.pert.name} | " + " | ".join(cells) + " |")
    out.append("")
    return out


# perturbations that apply to one sensor alone (the Tan windows have the right shank only for the events)
_TAN_GROUPS = ("invariant", "tolerated")
_TAN_SKIP = ("time shift", "sensor order", "clock offset", "packet loss", "tiled")


def tan_table(perts: list[Perturbation], seed: int, quick: bool) -> list[str]:
    """Heel strike and toe-off of the Tan et al. right-shank windows (:func:`pipeline.phases.detect_gait_events` on
    the shank's principal-axis rate, as :func:`bench.accuracy.real_tables`) under the single-sensor perturbations:
    errors against the force plate and the largest change against the unperturbed detection [ms]."""
    from bench.real_data import TAN_DIR, load_tan_steps, real_data_available
    from pipeline.phases import detect_gait_events, shank_sagittal_dps
    if not real_data_available(TAN_DIR):
        return ["_Tan et al. recordings absent (../shared/data/real): skipped._", ""]
    windows = load_tan_steps()

    def nearest(st: RawSensorStream, hs_s: float, to_s: float) -> tuple[float, float]:
        gyr, acc = _si(st)
        ev = detect_gait_events(shank_sagittal_dps(np.rad2deg(gyr)), float(st.fs_hz), min_bout_peaks=1,
                                shank_acc_mps2=acc)
        t = np.asarray(st.t_s, float)
        out = []
        for x, ref in ((ev.hs, hs_s), (ev.to, to_s)):
            tx = t[x[x >= 0]]
            out.append(float(tx[np.argmin(np.abs(tx - ref))]) if tx.size else math.nan)
        return out[0], out[1]

    streams = [RawSensorStream(sensor_id="R_SHANK", leg="right", segment="shank", fs_hz=w.fs_hz, t_s=w.t_s,
                               gyr=w.shank_gyr_dps, acc=w.shank_acc_mps2, gyro_unit="deg/s", acc_unit="m/s2")
               for w in windows]
    truth = [(float(w.t_s[w.hs_idx]), float(w.t_s[min(w.to_idx, w.t_s.size - 1)])) for w in windows]
    base = [nearest(st, hs, to) for st, (hs, to) in zip(streams, truth, strict=True)]
    out = ["### Perturbations of the real Tan et al. treadmill steps (right shank, force-plate events)", "",
           f"{len(windows)} step windows; per perturbation and repetition every window is perturbed and its events "
           "detected again. Found: windows with a heel strike / toe-off; errors against the force plate (mean "
           "abs, worst repetition); Δ: largest change of any window's event against the unperturbed detection.", "",
           "| group | perturbation | reps | HS found | HS err mean abs (ms) | ΔHS max (ms) | TO found "
           "| TO err mean abs (ms) | ΔTO max (ms) |", "|---|---|---|---|---|---|---|---|---|"]
    rows = [("-", "unperturbed", 1, [base])]
    for p in perts:
        if p.group not in _TAN_GROUPS or any(k in p.name for k in _TAN_SKIP):
            continue
        rng = np.random.default_rng([seed, sum(map(ord, p.name)), 1])
        reps = min(p.reps, 2) if quick else p.reps
        runs = []
        for _ in range(reps):
            runs.append([nearest(p.apply([st], rng).streams[0], hs, to)
                         for st, (hs, to) in zip(streams, truth, strict=True)])
        rows.append((p.group, p.name, reps, runs))
    for group, name, reps, runs in rows:
        cells = []
        for k in (0, 1):
            found = min(sum(math.isfinite(r[i][k]) for i in range(len(windows))) for r in runs)
            err = max(float(np.nanmean([abs(r[i][k] - truth[i][k]) for i in range(len(windows))])) for r in runs)
            d = max(float(np.nanmax([abs(r[i][k] - base[i][k]) for i in range(len(windows))])) for r in runs)
            cells += [f"{found}/{len(windows)}", f"{1000 * err:.0f}", f"{1000 * d:.0f}"]
        out.append(f"| {group} | {name} | {reps} | " + " | ".join(cells) + " |")
    out.append("")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.real_perturb", description=__doc__.split("\n\n")[0])
    ap.add_argument("--estimators", default=",".join(ESTIMATORS),
                    help=f"comma list (default: {','.join(ESTIMATORS)}); the first gets the full table")
    ap.add_argument("--activity", default="walking", choices=("walking", "unknown", "running"),
                    help="the upload's declared activity (default walking: the recording is a walk)")
    ap.add_argument("--seed", type=int, default=0, help="random draws of the perturbations (default 0)")
    ap.add_argument("--quick", action="store_true", help="2 repetitions at most and `auto` only (smoke run)")
    ap.add_argument("--only", default="", help="comma list of substrings: run only perturbations whose name has one")
    args = ap.parse_args(argv)
    from bench.real_data import BIOMECHZOO_CSV, load_biomechzoo, real_data_available
    if not real_data_available(BIOMECHZOO_CSV):
        print("_biomechZoo recording absent (../shared/data/real): skipped._")
        return 0
    ests = ["auto"] if args.quick else [e.strip() for e in args.estimators.split(",") if e.strip()]
    perts = perturbations()
    if args.only:
        keys = [k.strip() for k in args.only.split(",") if k.strip()]
        perts = [p for p in perts if any(k in p.name for k in keys)]
    streams, vicon = load_biomechzoo()
    noise_dps = float(np.rad2deg(np.median([native_noise_sd(_si(s)[0]) for s in streams])))
    noise_g = float(np.median([native_noise_sd(_si(s)[1]) for s in streams]) / G_MPS2)
    t0 = time.perf_counter()
    base = {e: process_session(streams, activity=args.activity, estimator=e) for e in ests}
    base_scores = {e: {leg: vicon_scores(base[e].legs[leg], vicon[leg], 0.0, None) for leg in LEGS} for e in ests}
    rows: dict[str, list[RowResult]] = {e: [] for e in ests}
    for k, p in enumerate(perts, 1):
        reps = min(p.reps, 2) if args.quick else p.reps
        for e in ests:
            r = run_one(p, e, streams, vicon, base[e], args.seed, args.activity, reps)
            r.pert = dataclasses.replace(p, reps=reps)
            rows[e].append(r)
        r = rows[ests[0]][-1]
        _log(f"[{k}/{len(perts)}] {p.name}: {ests[0]} strides "
             f"{[min(r.legs[leg].strides) if r.legs[leg].strides else 0 for leg in LEGS]}, max dpeak "
             f"{max(r.legs['left'].d_peak, r.legs['right'].d_peak):.2f} deg "
             f"(elapsed {time.perf_counter() - t0:.0f} s)")
    out = ["### Perturbations of the real biomechZoo trial", "",
           f"`python -m bench.real_perturb{' --quick' if args.quick else ''}` (activity `{args.activity}`, seed "
           f"{args.seed}). Δ: change against the unperturbed run of the same estimator, max over repetitions "
           f"(strides matched by heel strike within {MATCH_S:g} s; Δtrace: RMS over the common samples). "
           f"✗: an invariant perturbation moving a value by more than {INVARIANT_DEG:g} deg, a tolerated one by more "
           f"than {TOLERATED_DEG:g} deg, a lost stride that no hole longer than the bridge limit "
           f"({WALKING.prepare.periodic_bridge_s:g} s) comes within {KEEP_MARGIN_S:g} s of (`keepable`), an extra "
           f"stride, or a stored angle outside [{BAND_DEG[0]:g}, {BAND_DEG[1]:g}] deg. Tolerated rows are judged on "
           f"the strides trends take (quality >= {TREND_QUALITY:g}); strides flagged below it may move more. Vicon "
           "columns: worst repetition, against the leg the output is labelled with (what a clinician reads). Label "
           "rows: Δ against the unperturbed leg the output follows (named when it is the other leg); `not "
           "detected`: no warning. Masked: samples the pipeline masked as implausible (summed over legs, max over "
           f"repetitions). Native noise floor (:func:`native_noise_sd`, median over sensors and axes): gyro "
           f"{noise_dps:.2f} deg/s, accelerometer {noise_g * 1000:.1f} mg.", ""]
    for e in ests:
        out += table_main(rows[e], base, base_scores)
    if len(ests) > 1:
        out += table_compact(rows)
    out += tan_table(perts, args.seed, args.quick)
    print("\n".join(out))
    _log(f"done in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
