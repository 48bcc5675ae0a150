"""The speed reference of ``bench/speed.py``: a plain implementation of the two published algorithms gaitmon builds
on, straightforward numpy on the whole session held in memory. Not imported by the pipeline.

- joint axes: Seel et al. 2014 (Eq. 1-2 family; Rhudy et al. 2024 Eq. 2-3): Gauss-Newton on the hinge constraint
  e_i = ||g1_i x j1|| - ||g2_i x j2|| over every sample, axes in spherical coordinates, started from each segment's
  principal rotation axis;
- knee angle: Allseits et al. 2018 (GO, Sect. 2.2): knee angular velocity g1.j1 - g2.j2, low-passed (Butterworth,
  zero phase), integrated, and reset to zero once per stride at the last negative-to-positive crossing of the
  knee angular velocity between mid-stance and toe-off (found from the shank angular velocity's mid-swing peaks).

No gap handling, clock correction, accelerometer angle, fallback or quality: the bare algorithms, as a floor for
what processing a session costs.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import butter, find_peaks, sosfiltfilt

from pipeline.types import RawSensorStream


def _rad_s(s: RawSensorStream) -> np.ndarray:
    g = np.asarray(s.gyr, dtype=np.float64)
    return np.deg2rad(g) if s.gyro_unit == "deg/s" else g


def common_grid(thigh: RawSensorStream, shank: RawSensorStream) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Both gyros [rad/s] linearly interpolated onto one uniform grid over the common span."""
    fs = float(thigh.fs_hz)
    t = np.arange(max(thigh.t_s[0], shank.t_s[0]), min(thigh.t_s[-1], shank.t_s[-1]), 1.0 / fs)
    out = []
    for s in (thigh, shank):
        g = _rad_s(s)
        out.append(np.stack([np.interp(t, s.t_s, g[:, i]) for i in range(3)], axis=1))
    return t, out[0], out[1], fs


def _sph(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    phi, theta = x
    j = np.array([np.cos(phi) * np.cos(theta), np.cos(phi) * np.sin(theta), np.sin(phi)])
    d_phi = np.array([-np.sin(phi) * np.cos(theta), -np.sin(phi) * np.sin(theta), np.cos(phi)])
    d_theta = np.array([-np.cos(phi) * np.sin(theta), np.cos(phi) * np.cos(theta), 0.0])
    return j, d_phi, d_theta


def seel_axes(g1: np.ndarray, g2: np.ndarray, iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Knee axis in the thigh and shank frames by Gauss-Newton on Seel's Eq. 2 over all samples."""
    x = []
    for g in (g1, g2):
        v = np.linalg.svd(g, full_matrices=False)[2][0]
        x += [np.arcsin(np.clip(v[2], -1, 1)), np.arctan2(v[1], v[0])]
    x = np.array(x)
    for _ in range(iterations):
        cols, norms = [], []
        for k, g in enumerate((g1, g2)):
            j, dp, dt = _sph(x[2 * k:2 * k + 2])
            c = np.cross(g, j)
            n = np.maximum(np.linalg.norm(c, axis=1), 1e-9)
            sign = 1.0 if k == 0 else -1.0
            cols += [sign * np.einsum("ij,ij->i", c, np.cross(g, dp)) / n,
                     sign * np.einsum("ij,ij->i", c, np.cross(g, dt)) / n]
            norms.append(n)
        e = norms[0] - norms[1]
        jac = np.stack(cols, axis=1)
        step = np.linalg.solve(jac.T @ jac, -jac.T @ e)  # the Gauss-Newton normal equations
        x = x + step
        if np.max(np.abs(step)) < 1e-6:  # rad: far below any physical effect of the axis
            break
    j1, j2 = _sph(x[:2])[0], _sph(x[2:])[0]
    w2 = g2 @ j2
    if -np.percentile(w2, 0.5) > np.percentile(w2, 99.5):
        j2 = -j2  # shank swing forward (mid-swing) positive
    if np.dot(g1 @ j1, g2 @ j2) < 0:
        j1 = -j1
    return j1, j2


def go_strides(g1: np.ndarray, g2: np.ndarray, j1: np.ndarray, j2: np.ndarray, fs: float
               ) -> tuple[np.ndarray, list[tuple[int, int, float]]]:
    """GO knee angle [deg] and the strides (ZAU to next ZAU, with peak flexion [deg])."""
    sos = butter(2, 20.0 / (0.5 * fs), output="sos")
    kav = sosfiltfilt(sos, np.rad2deg(g1 @ j1 - g2 @ j2))
    sav = sosfiltfilt(butter(2, 4.0 / (0.5 * fs), output="sos"), np.rad2deg(g2 @ j2))
    msw, _ = find_peaks(sav, height=100.0, distance=int(0.5 * fs))
    cross = np.flatnonzero((kav[:-1] < 0) & (kav[1:] >= 0)) + 1
    zau = []
    for k in range(1, msw.size):
        lo = (msw[k - 1] + msw[k]) // 2  # mid-stance: half-way between two mid-swings
        to = lo + int(np.argmin(sav[lo:msw[k]]))  # toe-off: the shank rate's minimum before swing
        c = cross[(cross > lo) & (cross <= to + int(0.05 * fs))]
        zau.append(int(c[-1]) if c.size else to)
    angle = np.concatenate(([0.0], np.cumsum(0.5 * (kav[1:] + kav[:-1])) / fs))
    strides = []
    for a, b in zip(zau[:-1], zau[1:], strict=False):
        seg = angle[a:b] - angle[a]
        angle[a:b] = seg
        if 0.5 * fs <= b - a <= 3.0 * fs:
            strides.append((a, b, float(seg.max())))
    return angle, strides


def process(streams: list[RawSensorStream]) -> dict[str, int]:
    """Strides per leg of a session (thigh and shank of each leg)."""
    out = {}
    for leg in ("left", "right"):
        seg = {s.segment: s for s in streams if s.leg == leg}
        if {"thigh", "shank"} - set(seg):
            continue
        _, g1, g2, fs = common_grid(seg["thigh"], seg["shank"])
        j1, j2 = seel_axes(g1, g2)
        _, strides = go_strides(g1, g2, j1, j2, fs)
        out[leg] = len(strides)
    return out
