"""Knee joint axes, joint centres and the accelerometer knee angle (Seel et al. 2014, written out as Eq. 1-7 in
Rhudy et al., Sensors 2024, 24, 695). Segment 1 is the THIGH, segment 2 the SHANK throughout this package.

Sign convention (the knee flexion rate ``g1.j1 - g2.j2`` is positive for flexion, for either leg and any mounting):

* the sign of ``j2`` is chosen so that the largest excursions of the shank's sagittal angular velocity ``g2.j2``
  are positive. In walking these are the mid-swing peaks, when the shank swings forward faster than anything else;
  in stance the shank rotates the other way (knee travelling forward over the foot), so stance is negative.
* the sign of ``j1`` is chosen so that ``g1.j1`` correlates positively with ``g2.j2`` (thigh and shank swing forward
  together in gait). Both axes then point in the same physical direction and the knee angle is the thigh's rotation
  about that axis minus the shank's; with the shank swinging forward counted positive, flexion is positive.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import leastsq
from scipy.stats import chi2

from pipeline.params import WALKING, AxesParams
from pipeline.prepare import PreparedLeg
from pipeline.signal_utils import away_from_holes, cross_rows, row_norm

_EPS = 1e-9  # guards divisions by a norm; far below any physical value


@dataclass(frozen=True)
class JointAxes:
    """Knee axis in both sensor frames (unit 3-vectors) and the Eq. 2 fit's residual."""

    j1: np.ndarray  # thigh frame
    j2: np.ndarray  # shank frame
    rms_residual_dps: float
    n_samples: int
    # Seel's Eq. 2 hinge before ``j1``/``j2`` were levelled (:func:`fit_joint_axes`; None: ``j1``/``j2`` themselves)
    hinge_j1: np.ndarray | None = None
    hinge_j2: np.ndarray | None = None
    # the hinge leaned out of the level by more than ``AxesParams.level_lean_deg`` and ``j1``/``j2`` were turned back:
    # the knee's motion is no hinge's
    leaning: bool = False
    # how far the hinge axes leaned out of the level (thigh, shank) [deg]; None when no level was given
    lean_deg: tuple[float, float] | None = None

    def hinge(self) -> tuple[np.ndarray, np.ndarray]:
        """The axes of Seel's hinge constraint (Eq. 2), thigh and shank frame."""
        if self.hinge_j1 is None or self.hinge_j2 is None:
            return self.j1, self.j2
        return self.hinge_j1, self.hinge_j2



@dataclass(frozen=True)
class _Fit:
    """A least-squares solution and its cost (half the sum of squared residuals)."""

    x: np.ndarray
    cost: float


def _lm(fun: Callable[[np.ndarray], np.ndarray], jac: Callable[[np.ndarray], np.ndarray], x0: np.ndarray,
        tol: float = 1e-8) -> _Fit:
    """MINPACK's Levenberg-Marquardt with an analytic Jacobian (lmder), called as
    ``least_squares(fun, x0, jac=jac, method="lm", max_nfev=200)`` calls it (same tolerances and limits, so the same
    iterates and solution) without that wrapper's per-call set-up and per-evaluation bookkeeping, which cost more
    than the residuals of a thousand samples. The same iterates since SciPy 1.16 (whose ``least_squares`` scales
    the variables as MINPACK does by default); raises ValueError like ``least_squares`` when ``fun(x0)`` is not
    finite. ``tol``: ftol, xtol and gtol alike."""
    if not np.isfinite(fun(x0)).all():
        raise ValueError("residuals are not finite at the initial point")
    x, _, info, _, _ = leastsq(fun, x0, Dfun=jac, full_output=True, ftol=tol, xtol=tol, gtol=tol, maxfev=200)
    f = info["fvec"]
    return _Fit(x=x, cost=0.5 * float(np.dot(f, f)))


@dataclass(frozen=True)
class JointCentres:
    """Sensor positions relative to the knee centre (Seel Eq. 5) and the fit's residual."""

    o1: np.ndarray  # position of the thigh sensor relative to the knee centre, thigh frame [m]
    o2: np.ndarray  # position of the shank sensor relative to the knee centre, shank frame [m]
    rms_residual_mps2: float
    absolute: bool  # True when both in-plane sensor->knee directions are well defined (absolute angle possible)
    # constant accelerometer biases fitted with the centres (thigh / shank frame) [m/s^2]: nuisance parameters that
    # keep the centres from absorbing the biases (:func:`fit_joint_centres`), not applied to the angles
    b1: np.ndarray = field(default_factory=lambda: np.zeros(3))
    b2: np.ndarray = field(default_factory=lambda: np.zeros(3))


def select_fit_samples(g1: np.ndarray, g2: np.ndarray, valid: np.ndarray,
                       params: AxesParams = WALKING.axes, step: int = 1) -> np.ndarray:
    """A bounded, deterministic sample set (indices) for the axis/centre fits: the most dynamic samples of each of
    ``fit_chunks`` equal time chunks, so the cost does not grow with session length and the set spans the session.
    ``g1``, ``g2`` (N, 3) gyros [rad/s], ``valid`` (N,) bool; ``step``: only every ``step``-th sample is a
    candidate (:func:`centre_fit_step`)."""
    max_samples, chunks = params.max_fit_samples, params.fit_chunks
    idx = np.flatnonzero(valid)
    if step > 1:
        idx = idx[idx % step == 0]
    if idx.size <= max_samples:
        return idx
    mag = row_norm(g1)[idx] + row_norm(g2)[idx]  # row-wise, so norming first and gathering once is the same
    per_chunk = int(np.ceil(max_samples / chunks))
    picked = []
    for part, m in zip(np.array_split(idx, chunks), np.array_split(mag, chunks), strict=True):
        if part.size <= per_chunk:
            picked.append(part)
        else:
            picked.append(part[np.argpartition(-m, per_chunk - 1)[:per_chunk]])
    return np.sort(np.concatenate(picked))


def centre_fit_step(fs_hz: float, params: AxesParams = WALKING.axes) -> int:
    """Candidate spacing [samples] of the joint-centre fit's sample set (:func:`select_fit_samples`): one candidate
    per ``1 / centre_fit_hz``. Its inputs are low-passed at ``fit_cutoff_hz``, so neighbouring samples of a fast
    recording repeat each other; at 200 Hz the budget's most dynamic samples bunched into half the time of those at
    100 Hz, and Eq. 5 lost the sensor position on 5 of 80 legs of an independent simulator (17-44 cm off, levels up
    to 27 deg off) that it found at 100 Hz."""
    return max(int(round(fs_hz / params.centre_fit_hz)), 1)


def _sph(phi: float, theta: float) -> np.ndarray:
    return np.array([np.cos(phi) * np.cos(theta), np.cos(phi) * np.sin(theta), np.sin(phi)])


def _sph_derivs(phi: float, theta: float) -> tuple[np.ndarray, np.ndarray]:
    d_phi = np.array([-np.sin(phi) * np.cos(theta), -np.sin(phi) * np.sin(theta), np.cos(phi)])
    d_theta = np.array([-np.cos(phi) * np.sin(theta), np.cos(phi) * np.cos(theta), 0.0])
    return d_phi, d_theta


def _to_sph(j: np.ndarray) -> tuple[float, float]:
    j = j / np.linalg.norm(j)
    return float(np.arcsin(np.clip(j[2], -1.0, 1.0))), float(np.arctan2(j[1], j[0]))


class _AxisProblem:
    """Seel Eq. 2 residuals and their analytic Jacobian on one sample set, sharing work between the two: MINPACK
    asks for the Jacobian at the point whose residuals it has just evaluated, so ``g.j`` and ``||g x j||`` are kept
    from that call, and ``|g|^2`` is computed once per sample set instead of once per evaluation. Same arithmetic
    as evaluating each from scratch, so the same solver path and result."""

    def __init__(self, g1: np.ndarray, g2: np.ndarray) -> None:
        self.g = (g1, g2)
        self.gg = (np.einsum("ij,ij->i", g1, g1), np.einsum("ij,ij->i", g2, g2))
        self._x: np.ndarray | None = None
        self._parts: list[tuple[np.ndarray, np.ndarray]] = []

    def _eval(self, x: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        if self._x is None or x.shape != self._x.shape or not (x == self._x).all():
            parts = []
            for k in range(2):
                gj = self.g[k] @ _sph(x[2 * k], x[2 * k + 1])
                parts.append((gj, np.sqrt(np.maximum(self.gg[k] - gj ** 2, _EPS))))
            self._x, self._parts = np.array(x, dtype=float), parts
        return self._parts

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """||g1 x j1|| - ||g2 x j2|| per sample, via ||g x j||^2 = |g|^2 - (g.j)^2 for unit j."""
        (_, n1), (_, n2) = self._eval(x)
        return n1 - n2

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """d||g x j||/dj = -(g.j) g / ||g x j||, chained with the spherical map."""
        parts = self._eval(x)
        jac = np.empty((self.g[0].shape[0], 4))
        for k, sign in ((0, 1.0), (1, -1.0)):
            g = self.g[k]
            gj, norm = parts[k]
            d_phi, d_theta = _sph_derivs(x[2 * k], x[2 * k + 1])
            coef = -sign * gj / norm
            jac[:, 2 * k] = coef * (g @ d_phi)
            jac[:, 2 * k + 1] = coef * (g @ d_theta)
        return jac


class _AxisLagProblem:
    """Seel Eq. 2 with the shank's clock lag ``tau`` [s] as a fifth unknown beside the two axes' spherical angles:
    ``||g1 x j1|| - ||(g2 + tau gd2) x j2||`` (the shank's rate ``tau`` later, to first order; ``gd2`` its Eq. 1
    derivative). A lag between the two sensors' stamps breaks the hinge constraint sample by sample; where the leg
    also moves out of its sagittal plane (hip ab/adduction and rotation, pelvis) the axes alone can absorb part of
    that misfit, tilting by degrees, and the lag then read with those axes is a fraction of the true one (on the
    simulator's ``joint_3d`` axis: 21 ms read as 7). Fitted together, the axes need not explain the lag."""

    def __init__(self, g1: np.ndarray, g2: np.ndarray, gd2: np.ndarray) -> None:
        self.g1, self.g2, self.gd2 = g1, g2, gd2

    def _parts(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        j1, j2 = _sph(x[0], x[1]), _sph(x[2], x[3])
        w2 = self.g2 + x[4] * self.gd2
        p1, p2 = self.g1 @ j1, w2 @ j2
        n1 = np.sqrt(np.maximum(np.einsum("ij,ij->i", self.g1, self.g1) - p1 ** 2, _EPS))
        n2 = np.sqrt(np.maximum(np.einsum("ij,ij->i", w2, w2) - p2 ** 2, _EPS))
        return w2, p1, p2, n1, n2

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Per sample ``||g1 x j1|| - ||w2 x j2||``, ``w2 = g2 + tau gd2``."""
        _, _, _, n1, n2 = self._parts(x)
        return n1 - n2

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """d||g x j||/dj = -(g.j) g / ||g x j|| (chained with the spherical map) and
        d||w2 x j2||/dtau = (w2.gd2 - (w2.j2)(gd2.j2)) / ||w2 x j2||."""
        w2, p1, p2, n1, n2 = self._parts(x)
        jac = np.empty((self.g1.shape[0], 5))
        for k, (g, p, n, sign) in enumerate(((self.g1, p1, n1, 1.0), (w2, p2, n2, -1.0))):
            d_phi, d_theta = _sph_derivs(x[2 * k], x[2 * k + 1])
            coef = -sign * p / n
            jac[:, 2 * k] = coef * (g @ d_phi)
            jac[:, 2 * k + 1] = coef * (g @ d_theta)
        j2 = _sph(x[2], x[3])
        jac[:, 4] = -(np.einsum("ij,ij->i", w2, self.gd2) - p2 * (self.gd2 @ j2)) / n2
        return jac


def principal_axis(g: np.ndarray) -> np.ndarray:
    """Dominant rotation axis of a segment (McGrath et al. 2018: in gait most angular velocity is sagittal)."""
    _, _, vt = np.linalg.svd(g, full_matrices=False)
    return vt[0]


def fit_joint_axes(g1_rps: np.ndarray, g2_rps: np.ndarray, valid: np.ndarray | None = None,
                   params: AxesParams = WALKING.axes,
                   up: tuple[np.ndarray, np.ndarray] | None = None, gd2_rps2: np.ndarray | None = None) -> JointAxes:
    """Joint axis of the knee in the thigh (``j1``) and shank (``j2``) sensor frames by Seel's Eq. 2
    (Rhudy et al. 2024, Eq. 2-3), solved by Levenberg-Marquardt (:func:`_lm`) on a bounded sample set.

    Initialised with each segment's principal rotation axis (McGrath et al. 2018) plus a few seeded restarts;
    deterministic. Signs follow the module convention (flexion rate ``g1.j1 - g2.j2`` positive). ``gd2_rps2``: the
    shank's angular acceleration (:func:`angular_acceleration` of ``g2_rps``): the solution is then refined with a
    thigh-shank clock lag fitted alongside (:class:`_AxisLagProblem`), for data whose clocks are not yet aligned.

    ``up``: per segment the direction the flexion axis is perpendicular to (:func:`level_directions`); each axis is
    then turned towards that plane until it leans out of it by ``AxesParams.level_lean_deg`` at most (``leaning``),
    and the hinge axes are kept as ``hinge_j1``/``hinge_j2`` for the clock cues. A real knee is no hinge: the tibia
    also turns about its long axis as the knee flexes (~0.15 deg per deg, the screw-home mechanism run backwards;
    bone-pin studies find ~9 deg over the gait cycle, Lafortune et al. 1992, Benoit et al. 2006), so the hinge that
    fits best is an oblique axis leaning towards the segments' long axes (10-15 deg per segment at that coupling on the
    simulator's ``joint_3d`` axis, 15-30 at twice it), the flexion rate about it takes in the axial rotation (swing
    peak +2.4 deg at twice the coupling), and with 3-D hip motion on top the hinge fit failed outright (recall
    0.73, peak errors of tens of degrees). The clinical flexion axis (Grood and Suntay 1983) is the femur's
    medio-lateral axis: horizontal when the knee is level.
    """
    valid = np.ones(g1_rps.shape[0], dtype=bool) if valid is None else valid
    idx = select_fit_samples(g1_rps, g2_rps, valid, params)
    if idx.size < 10:
        raise ValueError("too few samples to estimate the knee axis")
    g1, g2 = g1_rps[idx], g2_rps[idx]
    p1, p2 = principal_axis(g1), principal_axis(g2)
    starts = [np.array([*_to_sph(p1), *_to_sph(p2)])]
    rng = np.random.default_rng(0)
    for _ in range(params.n_restarts):
        starts.append(np.array([rng.uniform(-1.4, 1.4), rng.uniform(-np.pi, np.pi),
                                rng.uniform(-1.4, 1.4), rng.uniform(-np.pi, np.pi)]))
    # restarts on a quarter of the set, then the winner refined on all of it (bounded, deterministic cost)
    sub = slice(None, None, 4) if idx.size >= 400 else slice(None)
    best = None
    prob_sub = _AxisProblem(g1[sub], g2[sub])
    for x0 in starts:
        sol = _lm(prob_sub.residuals, prob_sub.jacobian, x0)
        if best is None or sol.cost < best.cost - 1e-12:
            best = sol
    assert best is not None
    prob = _AxisProblem(g1, g2)
    best = _lm(prob.residuals, prob.jacobian, best.x)
    if gd2_rps2 is not None:
        joint = _AxisLagProblem(g1, g2, gd2_rps2[idx])
        best = _lm(joint.residuals, joint.jacobian, np.append(best.x, 0.0))
    j1, j2 = _sph(best.x[0], best.x[1]), _sph(best.x[2], best.x[3])
    j1, j2 = orient_axes(j1, j2, g1_rps, g2_rps, mask=valid)
    rms = float(np.rad2deg(np.sqrt(2.0 * best.cost / idx.size)))
    if up is None:
        return JointAxes(j1=j1, j2=j2, rms_residual_dps=rms, n_samples=int(idx.size))
    lean = (_lean_deg(j1, up[0]), _lean_deg(j2, up[1]))
    if max(lean) > params.max_level_lean_deg:  # not the body's level (AxesParams.max_level_lean_deg)
        return JointAxes(j1=j1, j2=j2, rms_residual_dps=rms, n_samples=int(idx.size), lean_deg=lean)
    f1, f2 = (_level_axis(j, u, np.radians(params.level_lean_deg)) for j, u in ((j1, up[0]), (j2, up[1])))
    if f1 is j1 and f2 is j2:
        return JointAxes(j1=j1, j2=j2, rms_residual_dps=rms, n_samples=int(idx.size), lean_deg=lean)
    return JointAxes(j1=f1, j2=f2, rms_residual_dps=rms, n_samples=int(idx.size), hinge_j1=j1, hinge_j2=j2,
                     leaning=True, lean_deg=lean)


def median_principal_axis(g_rps: np.ndarray, runs: Sequence[tuple[int, int]]) -> np.ndarray:
    """One segment's dominant rotation axis (3,) over several runs of samples ``[a, b)`` of ``g_rps`` (N, 3): each
    run's :func:`principal_axis`, signs aligned with the pooled one, and their component-wise median, normalised.
    A pooled principal axis takes in every rotation of every run; the median leaves out the few runs that turn about
    another axis (a turn while running: single gait cycles 27-32 deg off, the pooled axis 1.8 deg, the median 0.1
    deg on the simulator). Runs of fewer than 3 samples are skipped; with fewer than 3 runs, the pooled axis."""
    parts = [g_rps[a:b] for a, b in runs if b - a >= 3]
    pooled = principal_axis(np.concatenate(parts)) if parts else principal_axis(g_rps)
    if len(parts) < 3:
        return pooled
    each = np.array([principal_axis(x) for x in parts])
    each *= np.where(each @ pooled < 0.0, -1.0, 1.0)[:, None]
    med = np.median(each, axis=0)
    return med / np.linalg.norm(med)


def fit_shank_axis(g1_rps: np.ndarray, g2_rps: np.ndarray, j1: np.ndarray, j2_start: np.ndarray
                   ) -> tuple[np.ndarray, float]:
    """Seel's Eq. 2 for the shank axis alone, the thigh's ``j1`` given: Levenberg-Marquardt over ``j2``'s two
    spherical angles from ``j2_start`` on the samples given ((M, 3) gyros [rad/s], M >= 10). Returns ``j2`` and the
    RMS residual [deg/s].

    With both axes free, a knee that is no hinge (the tibia turning about its long axis as the knee flexes) lets the
    two tilt together along a shallow valley of the cost; with one side held, that valley is gone."""
    prob = _AxisProblem(g1_rps, g2_rps)
    x1 = np.array(_to_sph(j1))

    def fun(y: np.ndarray) -> np.ndarray:
        return prob.residuals(np.concatenate((x1, y)))

    def jac(y: np.ndarray) -> np.ndarray:
        return prob.jacobian(np.concatenate((x1, y)))[:, 2:]

    sol = _lm(fun, jac, np.array(_to_sph(j2_start)))
    return _sph(float(sol.x[0]), float(sol.x[1])), float(np.rad2deg(np.sqrt(2.0 * sol.cost / g1_rps.shape[0])))


def refit_axes(g1_rps: np.ndarray, g2_rps: np.ndarray, j1: np.ndarray, j2: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Seel's Eq. 2 hinge on the samples given ((M, 3) gyros [rad/s], M >= 10), from ``j1``/``j2`` (a fit of more
    data), without restarts and to a tolerance of 1e-4 (enough to compare axes to a tenth of a degree; the session
    fit's 1e-8 took ~20 iterations), signs as they came (compare with ``|j . j'|``)."""
    prob = _AxisProblem(g1_rps, g2_rps)
    x = _lm(prob.residuals, prob.jacobian, np.array([*_to_sph(j1), *_to_sph(j2)]), tol=1e-4).x
    return _sph(x[0], x[1]), _sph(x[2], x[3])


def axis_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle [deg] between the lines of two axes (signs ignored: a hinge axis has no sign of its own)."""
    return float(np.degrees(np.arccos(min(1.0, abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b))))))


def mean_axis(axes: np.ndarray) -> np.ndarray:
    """The line through several unit axes (K, 3) whatever their signs: the principal eigenvector of sum j j^T."""
    return np.linalg.eigh(axes.T @ axes)[1][:, -1]


def _lean_deg(j: np.ndarray, up: np.ndarray) -> float:
    """How far [deg] the unit axis ``j`` leans out of the plane perpendicular to the unit vector ``up``."""
    return float(np.degrees(np.arcsin(min(1.0, abs(float(j @ up))))))


def _level_axis(j: np.ndarray, up: np.ndarray, max_lean_rad: float) -> np.ndarray:
    """``j`` turned towards the plane perpendicular to ``up`` until it leans out of it by ``max_lean_rad`` at most
    (unchanged when it leans less)."""
    if np.radians(_lean_deg(j, up)) <= max_lean_rad:
        return j
    lean = float(np.arcsin(np.clip(j @ up, -1.0, 1.0)))
    flat = j - (j @ up) * up
    flat = flat / np.linalg.norm(flat)
    keep = float(np.copysign(max_lean_rad, lean))
    return np.cos(keep) * flat + np.sin(keep) * up


def level_directions(acc1_mps2: np.ndarray, acc2_mps2: np.ndarray, valid: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray] | None:
    """Per segment the mean specific force over the session's valid samples (sensor frame, unit), the ``up`` of
    :func:`fit_joint_axes`: the knee's flexion axis is horizontal in quiet standing, sitting, lying on the back and,
    on average, over every gait cycle (the pelvis level, hip ab/adduction a few deg either way), and a segment's
    own accelerations in gait and posture changes lie mostly in its sagittal plane, so the mean of gravity plus
    acceleration is nearly perpendicular to the flexion axis. None without a usable mean (a sensor reading zeros)."""
    up1, up2 = mean_up(acc1_mps2, valid), mean_up(acc2_mps2, valid)
    return None if up1 is None or up2 is None else (up1, up2)


def mean_up(acc_mps2: np.ndarray, valid: np.ndarray) -> np.ndarray | None:
    """One segment's unit mean specific force (3,) over the valid samples of ``acc_mps2`` (N, 3), sensor frame: its
    up direction on average; None without a usable mean (a sensor reading zeros)."""
    m = acc_mps2[valid].mean(axis=0) if valid.any() else np.zeros(3)
    if not np.isfinite(m).all() or np.linalg.norm(m) < 1.0:
        return None
    return m / np.linalg.norm(m)


def axis_up(prep: PreparedLeg, params: AxesParams = WALKING.axes) -> tuple[np.ndarray, np.ndarray] | None:
    """The ``up`` of :func:`fit_joint_axes` for a prepared leg (:func:`level_directions` of its accelerometers),
    None when ``params.axis_level`` is off."""
    if not params.axis_level:
        return None
    return level_directions(prep.acc_thigh_mps2, prep.acc_shank_mps2, prep.valid)


def orient_axes(j1: np.ndarray, j2: np.ndarray, g1: np.ndarray, g2: np.ndarray,
                mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Apply the module sign convention: largest excursions of ``g2.j2`` positive, ``g1.j1`` correlated with it.
    ``mask``: use only these samples (projecting first and selecting after saves copying the (N, 3) gyros)."""
    w2 = g2 @ j2
    w1 = g1 @ j1
    if mask is not None:
        w1, w2 = w1[mask], w2[mask]
    if w2.size:
        lo, hi = np.percentile(w2, [0.5, 99.5])  # one partition for both order statistics
        if -lo > hi:
            j2 = -j2
            w2 = -w2
    if w1.size and float(np.dot(w1 - w1.mean(), w2 - w2.mean())) < 0:
        j1 = -j1
    return j1, j2


def orient_thigh_on_gait(j1: np.ndarray, j2: np.ndarray, g1: np.ndarray, g2: np.ndarray,
                         strides: list[tuple[int, int, int]], fs_hz: float) -> np.ndarray:
    """The sign of ``j1`` from gait only (the detected strides ``(hs, to, hs_next)``): the one under which the knee
    extends least beyond its mid-stance flexion over a stride (:func:`knee_dips_deg`, median over strides).

    In mid-stance the knee is near its fullest extension in every gait (Perry and Burnfield 2010: ~5 deg more at
    terminal stance and heel strike; in running mid-stance is the stance's flexion peak), so the right sign dips
    1-7 deg below it in walking and up to ~20 in running (the simulator's patterns). A wrong sign makes the knee
    angle the sum of the two segments' angles, which at heel strike (thigh and shank both forward) lies 30-45 deg
    below its mid-stance value in walking and 70-100 in running: such a knee would hyperextend by tens of degrees.
    The correlation of the two segments' angles (or rates) that this rule replaces is weak on real gait (rates: r
    0.15-0.25 on the biomechZoo trial; angles: r ~0 on some legs of an independent simulator, which then read as
    that sum). Squats, jumps or sit-to-stand never vote (``strides`` are gait strides). ``j1`` unchanged without
    strides."""
    dips = knee_dips_deg(g1 @ j1, g2 @ j2, strides, fs_hz)
    if dips is None:
        return j1
    return -j1 if float(np.median(dips[1])) < float(np.median(dips[0])) else j1


def knee_dips_deg(w1_rps: np.ndarray, w2_rps: np.ndarray, strides: list[tuple[int, int, int]], fs_hz: float
                  ) -> tuple[np.ndarray, np.ndarray] | None:
    """Per whole stride ``(hs, to, hs_next)`` (no non-finite rate inside), how far below its mid-stance value
    (half-way from heel strike to toe-off) the knee angle ``th1 - th2`` falls over the stride, and the same for
    ``-th1 - th2`` (the other sign of the thigh's axis): two (strides,) arrays [deg]. ``th`` is each segment's
    rate about its axis (N,) [rad/s, sampled at ``fs_hz``] integrated over the stride (:func:`_stride_angles_deg`).
    None without a whole stride."""
    found = _stride_angles_deg(w1_rps, w2_rps, strides, fs_hz)
    if found is None:
        return None
    (th1, th2), first, (a, t) = found
    mst = first + ((a + t) // 2 - a)
    out = []
    for sign in (1.0, -1.0):
        knee = sign * th1 - th2
        out.append(knee[mst] - np.minimum.reduceat(knee, first))
    return out[0], out[1]


def knee_excursion_deg(w1_rps: np.ndarray, w2_rps: np.ndarray, strides: list[tuple[int, int, int]], fs_hz: float
                       ) -> np.ndarray | None:
    """Per whole stride, how one-sided the knee angle ``th1 - th2`` (:func:`knee_dips_deg`) moves: its largest plus
    its least value minus twice its mean [deg] (strides,). A knee flexes away from near extension and back, and
    rests near extension for most of a stride: in walking 0-20 deg for the stance's 60 %, a swing peak of 40-60 deg.
    Medians over a leg's strides on this repository's simulator: +19 .. +22 deg in normal, slow and fast walking,
    +14 .. +15 with a stiff knee, +7 .. +9 in crouch gait; the negated angle reads as far below zero. None without
    a whole stride. One value per whole stride kept (:func:`_stride_angles_deg`)."""
    found = _stride_angles_deg(w1_rps, w2_rps, strides, fs_hz)
    if found is None:
        return None
    (th1, th2), first, _ = found
    knee = th1 - th2
    size = np.diff(np.append(first, knee.size))
    mean = np.add.reduceat(knee, first) / size
    return np.maximum.reduceat(knee, first) + np.minimum.reduceat(knee, first) - 2.0 * mean


def _stride_angles_deg(w1_rps: np.ndarray, w2_rps: np.ndarray, strides: list[tuple[int, int, int]], fs_hz: float
                       ) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray, tuple[np.ndarray, np.ndarray]] | None:
    """Each segment's rate about its axis (N,) [rad/s, sampled at ``fs_hz``] integrated over each whole stride
    ``(hs, to, hs_next)`` (no non-finite rate inside, toe-off inside), its drift removed as the angle returns after
    a stride: the two angles [deg] of every such stride's samples concatenated, the index of each stride's first
    sample in them, and those strides' ``hs`` and ``to``. Every stride's samples at once (O(N), no loop over
    strides). None without a whole stride."""
    arr = np.asarray(strides, dtype=np.int64).reshape(-1, 3)
    ok = np.isfinite(w1_rps) & np.isfinite(w2_rps)
    bad = np.concatenate(([0], np.cumsum(~ok)))
    a, t, b = arr[:, 0], arr[:, 1], arr[:, 2]
    keep = (b - a >= 2) & (bad[b + 1] == bad[a]) & (t > a) & (t < b)
    if not keep.any():
        return None
    a, t, b = a[keep], t[keep], b[keep]
    size = b - a + 1
    first = np.cumsum(size) - size
    sid = np.repeat(np.arange(a.size), size)
    k = np.arange(size.sum()) - np.repeat(first, size) + a[sid]
    ramp = (k - a[sid]) / (b - a)[sid]
    th = []
    for w in (w1_rps, w2_rps):
        c = np.cumsum(np.where(ok, w, 0.0)) / fs_hz
        th.append(np.degrees(c[k] - c[a][sid] - ramp * (c[b] - c[a])[sid]))
    return (th[0], th[1]), first, (a, t)


def hinge_rates(g1: np.ndarray, g2: np.ndarray, j1: np.ndarray, j2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample ``||g1 x j1||`` and ``||g2 x j2||`` (Seel Eq. 2): the angular speed perpendicular to the axis."""
    return row_norm(cross_rows(g1, j1)), row_norm(cross_rows(g2, j2))


@dataclass(frozen=True)
class LagEstimate:
    """One window's clock lag [s] and its standard error [s] from the cost curve's curvature (None where unknown)."""

    lag_s: float
    se_s: float | None = None


def estimate_sync_lag_s(g1: np.ndarray, g2: np.ndarray, j1: np.ndarray, j2: np.ndarray, valid: np.ndarray,
                        fs_hz: float, window: slice | None = None,
                        rates: tuple[np.ndarray, np.ndarray] | None = None, max_lag_s: float = WALKING.sync.max_lag_s,
                        centre_s: float = 0.0) -> float | None:
    """The lag [s] of :func:`sync_lag_estimate` (same arguments), None without a clear minimum."""
    est = sync_lag_estimate(g1, g2, j1, j2, valid, fs_hz, window, rates, max_lag_s, centre_s)
    return None if est is None else est.lag_s


def sync_lag_estimate(g1: np.ndarray, g2: np.ndarray, j1: np.ndarray, j2: np.ndarray, valid: np.ndarray,
                      fs_hz: float, window: slice | None = None,
                      rates: tuple[np.ndarray, np.ndarray] | None = None, max_lag_s: float = WALKING.sync.max_lag_s,
                      centre_s: float = 0.0, cutoff_hz: float = WALKING.axes.fit_cutoff_hz) -> LagEstimate | None:
    """Timestamp offset of the shank relative to the thigh [s], from Seel's hinge constraint (Eq. 2): for a hinge,
    the angular velocity perpendicular to the axis is the same vector in both segments, so ||g1 x j1|| = ||g2 x j2||
    sample by sample. A clock offset between the sensors shifts one against the other; the lag (within +-max_lag_s)
    minimising the mean squared mismatch, refined by a parabola through the three best lags, estimates it.
    Positive: shank events appear late on the common grid. None when the cost has no clear minimum (a leg that never
    leaves its joint plane carries no timing information here). Inputs low-passed gyros [rad/s]; ``window``
    restricts the samples compared (clock drift: one estimate per window). ``rates``: :func:`hinge_rates` of the
    whole ``g1``/``g2`` when already computed (several windows of one session), else computed here. ``centre_s``:
    the lags searched are ``centre_s +- max_lag_s`` (a drifting lag followed from window to window). The standard
    error is that of a least-squares delay (residual variance C0 at the minimum, curvature C'' of the cost per
    squared sample): var = 2 C0 / (N_eff C''), with N_eff the compared samples per correlation time of rates
    low-passed at ``cutoff_hz`` (1 / (2 cutoff_hz))."""
    if window is not None:
        valid = valid[window]
        if rates is None:
            g1, g2 = g1[window], g2[window]
        else:
            rates = (rates[0][window], rates[1][window])
    m1, m2 = hinge_rates(g1, g2, j1, j2) if rates is None else rates
    k_max = max(int(round(max_lag_s * fs_hz)), 2)
    k0 = int(round(centre_s * fs_hz))
    n = m1.shape[0]
    lo, hi = max(k_max - k0, 0), min(n - k_max - k0, n)  # every lag k0 +- k_max stays inside the arrays
    if hi - lo < 10 * k_max:
        return None
    idx = np.flatnonzero(valid[lo:hi]) + lo
    if idx.size < 10 * k_max:
        return None
    ok2 = valid.astype(bool)
    if idx.size == hi - lo and ok2.all():
        sel: np.ndarray | slice = slice(lo, hi)  # no masked sample: every lag compares the window's samples
    else:
        # the same samples at every lag: one whose partner at any searched lag falls in a hole is left out, so that
        # the cost curve measures the misalignment, not which samples each lag happens to compare (at 10 % packet
        # loss that had moved window lags by up to 12 ms)
        sel = idx[away_from_holes(ok2, k_max)[idx + k0]]
        if sel.size < 10 * k_max:
            return None
    # one lag at a time: the (lags, samples) matrix would take ~400 MB for a 53 s window at 2000 Hz
    a = m1[sel]
    cost = np.array([np.mean((a - m2[_shifted(sel, k)]) ** 2) for k in range(k0 - k_max, k0 + k_max + 1)])
    lag = _parabolic_minimum_s(cost, k_max, fs_hz) if np.isfinite(cost).all() else None
    if lag is None:
        return None
    b = int(np.argmin(cost))
    curvature = cost[b - 1] - 2 * cost[b] + cost[b + 1]
    n_eff = a.shape[0] / (fs_hz / (2 * cutoff_hz))
    se = float(np.sqrt(2 * cost[b] / (n_eff * curvature)) / fs_hz) if curvature > 0 else None
    return LagEstimate(lag + k0 / fs_hz, se)


def _shifted(sel: np.ndarray | slice, k: int) -> np.ndarray | slice:
    """``sel`` (indices or a slice) moved by ``k`` samples."""
    return slice(sel.start + k, sel.stop + k) if isinstance(sel, slice) else sel + k


ANGULAR_ACCELERATION_HALF_WIDTH = 2
"""Samples on either side of a sample that :func:`angular_acceleration` (Seel Eq. 1, five points) reads."""


def angular_acceleration(g: np.ndarray, fs_hz: float) -> np.ndarray:
    """Seel Eq. 1 (Rhudy et al. 2024, Eq. 1): five-point central difference; one-sided at the ends."""
    if g.shape[0] < 5:
        return np.gradient(g, 1.0 / fs_hz, axis=0)
    gd = np.empty_like(g, dtype=float)
    gd[2:-2] = (g[:-4] - 8.0 * g[1:-3] + 8.0 * g[3:-1] - g[4:]) * (fs_hz / 12.0)
    # the two samples at each end as np.gradient gives them (its values there depend on three samples only)
    gd[:2] = np.gradient(g[:3], 1.0 / fs_hz, axis=0)[:2]
    gd[-2:] = np.gradient(g[-3:], 1.0 / fs_hz, axis=0)[1:]
    return gd


def _skew(v: np.ndarray) -> np.ndarray:
    """(N,3) -> (N,3,3) cross-product matrices."""
    z = np.zeros(v.shape[0])
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], -1),
                     np.stack([v[:, 2], z, -v[:, 0]], -1),
                     np.stack([-v[:, 1], v[:, 0], z], -1)], axis=1)


def gamma_matrices(g: np.ndarray, gd: np.ndarray) -> np.ndarray:
    """Seel's Gamma_g(o) = g x (g x o) + gdot x o is linear in o: returns M with Gamma = M @ o, (N,3,3)."""
    sg = _skew(g)
    return sg @ sg + _skew(gd)


def _centre_split(x: np.ndarray, a1: np.ndarray, m1: np.ndarray, a2: np.ndarray,
                  m2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``a - b - M o`` of both segments; ``x`` = (o1, o2) or (o1, o2, b1, b2)."""
    v1, v2 = a1 - np.einsum("nij,j->ni", m1, x[:3]), a2 - np.einsum("nij,j->ni", m2, x[3:6])
    if x.size == 12:
        v1, v2 = v1 - x[6:9], v2 - x[9:12]
    return v1, v2


def _biases(x: np.ndarray, basis: np.ndarray | None) -> np.ndarray:
    """(o1, o2, beta) -> (o1, o2, b1, b2) with b = basis @ beta: the biases of an observable subspace (6, k)."""
    return x if basis is None else np.concatenate([x[:6], basis @ x[6:]])


class _CentreProblem:
    """Seel Eq. 5 residual and Jacobian on one sample set, sharing ``a - M o`` and its norms between the two (MINPACK
    evaluates the Jacobian where it last evaluated the residuals); same arithmetic, same result.

    With ``bias_weight`` the unknowns are (o1, o2, b1, b2): each accelerometer's constant bias b_i is taken off its
    samples (``||a1 - b1 - Gamma1 o1|| - ||a2 - b2 - Gamma2 o2||``) and pulled towards 0 by the rows
    ``bias_weight * b``, a Gaussian prior on the bias (:func:`fit_joint_centres`). With ``bias_basis`` (6, k),
    orthonormal columns, the biases are ``bias_basis @ beta`` and the unknowns (o1, o2, beta, c), c a constant
    offset of the residual (the accelerometers' gain mismatch, :func:`observable_bias_basis`)."""

    def __init__(self, a1: np.ndarray, m1: np.ndarray, a2: np.ndarray, m2: np.ndarray, centre_reg: float,
                 bias_weight: float | None = None, bias_basis: np.ndarray | None = None,
                 offset_weight: float = 0.0) -> None:
        self.args = (a1, m1, a2, m2)
        self.centre_reg = centre_reg
        self.reg = centre_reg * np.sqrt(a1.shape[0])
        self.basis = bias_basis
        self.k = 6 if bias_weight is None else 6 + (6 if bias_basis is None else bias_basis.shape[1] + 1)
        self.w = np.full(self.k, self.reg)
        if bias_weight is not None:
            self.w[6:] = bias_weight
        if bias_basis is not None:
            self.w[-1] = offset_weight
        self._reg_rows = np.diag(self.w)  # the pulls' rows of the Jacobian
        self._x: np.ndarray | None = None
        self._parts: tuple[np.ndarray, ...] = ()

    def _eval(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        if self._x is None or x.shape != self._x.shape or not (x == self._x).all():
            v1, v2 = _centre_split(x if self.basis is None else _biases(x[:-1], self.basis), *self.args)
            self._x, self._parts = np.array(x, dtype=float), (v1, v2, row_norm(v1), row_norm(v2))
        return self._parts

    def residuals(self, x: np.ndarray) -> np.ndarray:
        _, _, n1, n2 = self._eval(x)
        n, k = n1.shape[0], self.k
        out = np.empty(n + k)
        np.subtract(n1, n2, out=out[:n])
        if self.basis is not None:
            out[:n] -= x[-1]
        np.multiply(self.w, x, out=out[n:])
        return out

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        v1, v2, n1, n2 = self._eval(x)
        _, m1, _, m2 = self.args
        n, k = n1.shape[0], self.k
        n1, n2 = np.maximum(n1, _EPS)[:, None], np.maximum(n2, _EPS)[:, None]
        # written into one preallocated array: the values of the stacked blocks, without the stacking copies
        out = np.empty((n + k, k))
        u1, u2 = v1 / n1, v2 / n2
        out[:n, :3] = np.einsum("ni,nij->nj", u1, m1)
        np.negative(out[:n, :3], out=out[:n, :3])
        out[:n, 3:6] = np.einsum("ni,nij->nj", u2, m2)
        if k > 6:
            if self.basis is None:
                np.negative(u1, out=out[:n, 6:9])
                out[:n, 9:12] = u2
            else:
                out[:n, 6:-1] = np.hstack([-u1, u2]) @ self.basis
                out[:n, -1] = -1.0
        out[n:] = self._reg_rows
        return out


def _centre_resid(x: np.ndarray, a1: np.ndarray, m1: np.ndarray, a2: np.ndarray, m2: np.ndarray) -> np.ndarray:
    """Seel Eq. 5 residual per sample: ||a1 - Gamma1(o1)|| - ||a2 - Gamma2(o2)|| (with ``x`` of 12 entries, the
    biases b_i taken off a_i first). The pull rows are left off: the cost is flat when both centres slide along the
    axis (Eq. 5's final projection), and the fit's weak pull of o towards 0 keeps the solver from wandering along
    that valley to metres."""
    return np.subtract(*(row_norm(v) for v in _centre_split(x, a1, m1, a2, m2)))


def _lsq_centres(x0: np.ndarray, a1: np.ndarray, m1: np.ndarray, a2: np.ndarray, m2: np.ndarray,
                 centre_reg: float, bias_weight: float | None = None, bias_basis: np.ndarray | None = None,
                 offset_weight: float = 0.0) -> _Fit:
    """Eq. 5 least squares from ``x0``: (o1, o2), or (o1, o2, b1, b2) with ``bias_weight``, or (o1, o2, beta, c)
    with ``bias_basis`` too (:class:`_CentreProblem`)."""
    prob = _CentreProblem(a1, m1, a2, m2, centre_reg, bias_weight, bias_basis, offset_weight)
    return _lm(prob.residuals, prob.jacobian, x0)


def observable_bias_basis(x: np.ndarray, a1: np.ndarray, m1: np.ndarray, a2: np.ndarray, m2: np.ndarray,
                          params: AxesParams = WALKING.axes) -> np.ndarray:
    """Orthonormal directions (6, k) of the two accelerometers' biases (b1, b2) that the Eq. 5 samples determine
    well enough to fit, linearised at the bias-free centres ``x`` = (o1, o2); the other directions stay at 0.

    Information: the Gauss-Newton information of the biases with the nuisances profiled out, S = J~^T J~ with
    J~ = J_b - J_o (J_o^T J_o + D)^-1 J_o^T J_b (J_o: the centres' columns and a constant offset's; D the centre
    pull). Its white-noise scale would trust every sample as independent, but the misfit of Eq. 5 (soft tissue,
    residual clock offset, impacts) is correlated within a stretch of gait, so the score covariance M is taken
    cluster-robust over ``fit_chunks`` contiguous blocks of the (time-ordered) samples (sandwich estimator, Liang &
    Zeger 1986, Biometrika 73:13; Cameron & Miller 2015, J. Hum. Resour. 50:317), giving the effective information
    I = S M^-1 S. A direction w with eigenvalue mu of I is kept when the posterior SD under the prior,
    (mu + 1/sigma_b^2)^-1/2, is below ``centre_bias_sd_ratio`` times the prior SD sigma_b: there the data, not the
    prior, set the bias."""
    n = a1.shape[0]
    sigma_b = params.centre_bias_prior_mps2
    groups = min(params.fit_chunks, n // 10)
    if sigma_b <= 0 or groups < 8:
        return np.zeros((6, 0))
    prob = _CentreProblem(a1, m1, a2, m2, params.centre_reg, bias_weight=1.0)
    x12 = np.concatenate([x[:6], np.zeros(6)])
    r = prob.residuals(x12)[:n]
    jac = prob.jacobian(x12)[:n]
    # the centres and a constant offset of the residual are profiled out: a gain mismatch between the two
    # accelerometers (consumer MEMS: 1-3 %, 0.1-0.3 m/s^2 at 1 g) offsets ||a1|| - ||a2|| by a near-constant, and a
    # bias direction whose regressor is near-constant (seen only through u_i's small tilt by the bias itself) would
    # take it up
    jo = np.column_stack([jac[:, :6], np.ones(n)])
    jb = jac[:, 6:]
    jt = jb - jo @ np.linalg.solve(jo.T @ jo + np.diag(np.r_[prob.w[:6] ** 2, 0.0]), jo.T @ jb)
    s = jt.T @ jt
    # residual after the (unconstrained, linearised) step in all unknowns, so that the true biases and offset do not
    # count as misfit
    full = np.column_stack([jo, jb])
    e = r - full @ np.linalg.lstsq(full.T @ full + np.diag(np.r_[prob.w[:6] ** 2, np.zeros(7)]), full.T @ r,
                                   rcond=None)[0]
    scores = np.stack([jt[blk].T @ e[blk] for blk in np.array_split(np.arange(n), groups)])
    scores -= scores.mean(axis=0)
    meat = scores.T @ scores * (groups / (groups - 1.0))
    meat += np.eye(6) * (1e-9 * max(float(np.trace(meat)), _EPS))
    info = s @ np.linalg.solve(meat, s)
    mu, vec = np.linalg.eigh(0.5 * (info + info.T))
    ratio = params.centre_bias_sd_ratio
    keep = mu * sigma_b ** 2 >= 1.0 / ratio ** 2 - 1.0
    return vec[:, keep]


def fit_joint_centres(a1: np.ndarray, g1: np.ndarray, gd1: np.ndarray, a2: np.ndarray, g2: np.ndarray,
                      gd2: np.ndarray, j1: np.ndarray, j2: np.ndarray, params: AxesParams = WALKING.axes
                      ) -> JointCentres:
    """Joint-centre positions by Seel's Eq. 5 (Rhudy et al. 2024, Eq. 5), least squares with analytic Jacobian,
    then shifted along the axes as in Eq. 5 (the cost is blind to sliding both along j). Inputs: a bounded sample set.

    Eq. 5 assumes bias-free accelerometers. A constant bias b_i of a few 0.01 g adds ``b1.u1 - b2.u2`` to the
    residual (u_i: direction of the knee-centre acceleration, mostly gravity, in sensor i's frame), which the
    centres would otherwise absorb, centimetres off in the joint plane. With ``AxesParams.centre_bias_prior_mps2``
    > 0 the fit is refined once more with the biases as unknowns, but only in the directions the samples make
    observable (:func:`observable_bias_basis`: along the knee axis, and the part common to both segments when they
    tilt together, the data see nothing), plus a constant offset of the residual (the accelerometers' gain
    mismatch), under a zero-mean Gaussian prior of that SD (maximum a posteriori: residual rows and prior rows
    ``(sigma_r / sigma_b) beta`` in one least-squares problem, sigma_r the residual RMS of the fit without biases).
    The biases are nuisance parameters: they correct the centres, not the angles (taken off the accelerometer angle
    too, they made 8 jumps in a row worse, peak bias -1.4 -> -2.2 deg).
    """
    m1, m2 = gamma_matrices(g1, gd1), gamma_matrices(g2, gd2)
    # MINPACK Levenberg-Marquardt (a 6-parameter problem; the trust-region solver's SVDs cost far more here).
    # The cost has mirrored local minima (a sensor->knee direction flipped), so a few seeded starts on a quarter of
    # the samples, then the best one refined on all of them.
    rng = np.random.default_rng(1)
    starts = [np.full(6, 1e-3)] + [rng.uniform(-0.25, 0.25, 6) for _ in range(params.n_centre_starts)]
    sub = slice(None, None, 4) if a1.shape[0] >= 400 else slice(None)
    args_sub = (a1[sub], m1[sub], a2[sub], m2[sub])
    reg = params.centre_reg
    trials = sorted((_lsq_centres(x0, *args_sub, reg) for x0 in starts), key=lambda r: r.cost)
    # the two best subset solutions refined on all samples: the subset alone can prefer a mirrored minimum
    sol = min((_lsq_centres(t.x, a1, m1, a2, m2, reg) for t in trials[:2]), key=lambda r: r.cost)
    # one trimming pass: a few samples (next to gaps, impacts) can carry metres-per-second-squared of misfit
    r = _centre_resid(sol.x, a1, m1, a2, m2)
    mad = float(np.median(np.abs(r - np.median(r)))) + 1e-9
    keep = np.abs(r - np.median(r)) < 6.0 * mad
    if keep.sum() >= 50 and not keep.all():
        a1, m1, a2, m2 = a1[keep], m1[keep], a2[keep], m2[keep]
        sol = _lsq_centres(sol.x, a1, m1, a2, m2, reg)
    x = sol.x
    basis = observable_bias_basis(x, a1, m1, a2, m2, params)
    offset = 0.0
    if basis.shape[1]:
        sigma_r = max(float(np.sqrt(np.mean(_centre_resid(x, a1, m1, a2, m2) ** 2))), _EPS)
        sd = np.r_[np.full(basis.shape[1], params.centre_bias_prior_mps2), params.centre_offset_prior_mps2]
        sub = _lsq_centres(np.concatenate([x, np.zeros(basis.shape[1] + 1)]), a1, m1, a2, m2, reg,
                           bias_weight=sigma_r / sd[0], bias_basis=basis, offset_weight=sigma_r / sd[-1]).x
        # a prior-predictive check (Box 1980, J. R. Stat. Soc. A 143:383): fitted biases the prior calls implausible
        # are misfit of another kind (a residual clock offset, a wrong centre minimum) that the bias terms absorb
        if float(np.sum((sub[6:] / sd) ** 2)) <= chi2.ppf(params.centre_bias_check_level, sd.size):
            x, offset = _biases(sub[:-1], basis), float(sub[-1])
    b1, b2 = (x[6:9], x[9:12]) if x.size == 12 else (np.zeros(3), np.zeros(3))
    o1h, o2h = x[:3], x[3:6]
    shift = (o1h @ j1 + o2h @ j2) / 2.0
    o1, o2 = o1h - j1 * shift, o2h - j2 * shift
    r = _centre_resid(x, a1, m1, a2, m2) - offset
    rms = float(np.sqrt(np.mean(r ** 2)))
    if max(np.linalg.norm(o1), np.linalg.norm(o2)) > params.max_lever_m:
        # not a body-worn sensor position: no lever-arm correction rather than a wrong one
        return JointCentres(o1=np.zeros(3), o2=np.zeros(3), rms_residual_mps2=rms, absolute=False)
    in_plane = min(np.linalg.norm(o1 - (o1 @ j1) * j1), np.linalg.norm(o2 - (o2 @ j2) * j2))
    return JointCentres(o1=o1, o2=o2, rms_residual_mps2=rms, absolute=bool(in_plane > 0.03), b1=b1, b2=b2)


def centre_residuals(centres: JointCentres, a1: np.ndarray, g1: np.ndarray, gd1: np.ndarray, a2: np.ndarray,
                     g2: np.ndarray, gd2: np.ndarray) -> np.ndarray:
    """Seel's Eq. 5 residual per sample (N,) [m/s^2] with fitted ``centres`` (their biases taken off):
    ``||a1 - b1 - Gamma1(o1)|| - ||a2 - b2 - Gamma2(o2)||``. Inputs as :func:`fit_joint_centres`'."""
    x = np.concatenate([centres.o1, centres.o2, centres.b1, centres.b2])
    return _centre_resid(x, a1, gamma_matrices(g1, gd1), a2, gamma_matrices(g2, gd2))


def fit_margin_mask(valid: np.ndarray, fs_hz: float, params: AxesParams = WALKING.axes) -> np.ndarray:
    """Samples at least ``fit_margin_s`` from any masked gap: the filters and Eq. 1 differences are unreliable
    within a few samples of one."""
    return away_from_holes(valid, max(int(params.fit_margin_s * fs_hz), 1))


def estimate_centre_lag_s(a1: np.ndarray, g1: np.ndarray, gd1: np.ndarray, a2: np.ndarray, g2: np.ndarray,
                          gd2: np.ndarray, j1: np.ndarray, j2: np.ndarray, far: np.ndarray, fs_hz: float,
                          window: slice, max_lag_s: float, params: AxesParams = WALKING.axes,
                          centres: np.ndarray | None = None, centre_s: float = 0.0,
                          min_depth: float = WALKING.sync.centre_depth,
                          step_s: float = WALKING.sync.centre_lag_step_s) -> tuple[float | None, np.ndarray | None]:
    """Timestamp offset of the shank relative to the thigh [s] (sign as :func:`estimate_sync_lag_s`) from Seel's
    joint-centre constraint (Eq. 5): both accelerometers, moved to the knee centre by ``Gamma o``, measure one
    acceleration, so ``||a1 - Gamma_1 o1|| = ||a2 - Gamma_2 o2||`` sample by sample. Unlike the hinge constraint
    (Eq. 2) this holds timing information in straight walking: the knee-centre acceleration swings by several
    m/s^2 each stride, most sharply at heel strike. The profile of the Eq. 5 cost over the lag: for each whole-sample
    lag the shank samples are shifted and the window's centres (o1, o2) fitted again (Levenberg-Marquardt from the
    neighbouring lag's centres and from those at ``centre_s``), so that the minimum does not depend on where the
    search starts: centres held at one lag's fit, or moved by one Gauss-Newton step, carry that lag's misfit and
    read only part of the way from it (running with 3-D knees and 20-40 ms offsets on an independent simulator: 40-90
    ms off, often of the wrong sign; refitted, within 5 ms). The lags are fitted every ``step_s`` first (and at both
    ends of the range), then every lag between the least of them and its two neighbours; a parabola through the
    three best lags. None without a clear minimum (:func:`one_valley`, on the first pass). Centres that fit no lag
    well (a thigh sensor 50 cm from the knee, which the fit's pull towards the knee keeps it from finding) and shocks
    that do not fit the rigid-body model give shallow or two-valleyed profiles with false minima 30-60 ms out; a
    broad valley (walking at 100 Hz on an independent simulator: -50 .. 0 ms around a true -32) still reads its
    least. Inputs on one grid: low-passed accelerations [m/s^2], gyros [rad/s] and their Eq. 1 derivatives,
    ``far`` the samples usable for a fit (:func:`fit_margin_mask`); only samples inside ``window`` are used. The lags
    searched are ``centre_s +- max_lag_s`` (a drifting lag followed from window to window). ``centres`` (o1, o2) start
    the fits when given (and are returned as given), else they are fitted at the lag ``centre_s`` on the window's
    samples (:func:`fit_joint_centres`, with its restarts). Returns the lag and those centres (None where the window
    has too few samples)."""
    k_max = max(int(round(max_lag_s * fs_hz)), 2)
    k0 = int(round(centre_s * fs_hz))
    n = g1.shape[0]
    usable = np.zeros(n, dtype=bool)
    lo = max(window.start or 0, k_max - k0, 0)
    hi = min(window.stop if window.stop is not None else n, n - k_max - k0, n)
    if hi - lo < 10 * k_max:
        return None, None
    usable[lo:hi] = far[lo:hi]
    idx = select_fit_samples(g1, g2, usable, params)
    if idx.size < 10 * k_max:
        return None, None
    # no accelerometer biases in the profile: refitted at every lag they absorb part of the offset (straight
    # walking, 15 ms injected: 18.9 ms read; none injected: -8 ms invented), and held at the zero-lag fit's values
    # they carry that fit's timing misfit (15 ms read as 4.9)
    span = np.arange(idx[0] + k0 - k_max, idx[-1] + k0 + k_max + 1)  # every shank sample a lag may reach
    m1, m2 = gamma_matrices(g1[idx], gd1[idx]), gamma_matrices(g2[span], gd2[span])
    at = idx + k0  # the shank's samples at the lag ``centre_s``
    if centres is None:
        first = fit_joint_centres(a1[idx], g1[idx], gd1[idx], a2[at], g2[at], gd2[at], j1, j2,
                                  dataclasses.replace(params, centre_bias_prior_mps2=0.0))
        centres = np.concatenate([first.o1, first.o2])
    if min(int(far[idx + k].sum()) for k in range(k0 - k_max, k0 + k_max + 1)) < 10 * k_max:
        return None, centres
    cost = np.full(2 * k_max + 1, np.nan)  # by lag k0 - k_max .. k0 + k_max
    fitted: dict[int, np.ndarray] = {}

    def fit_lag(k: int, from_k: int) -> None:
        """The profile at lag ``k``, started from the centres at ``centre_s`` and from the fitted lag ``from_k``'s."""
        ok = far[idx + k]
        rows = (a1[idx[ok]], m1[ok], a2[idx[ok] + k], m2[idx[ok] + k - span[0]], params.centre_reg)
        neighbour = fitted.get(from_k)
        starts = (centres,) if neighbour is None else (neighbour, centres)
        best = min((_lsq_centres(x0, *rows) for x0 in starts), key=lambda f: f.cost)
        fitted[k] = best.x
        cost[k - k0 + k_max] = 2.0 * best.cost / int(ok.sum())  # with the centres' pull, as _CentreProblem weighs it

    step = max(int(round(step_s * fs_hz)), 1)
    coarse = np.unique(np.r_[np.arange(0, k_max, step), k_max])  # offsets from k0 outwards, both ends included
    # outwards from ``centre_s``: each lag starts from its inner neighbour's centres (a continuous path of minima)
    fit_lag(k0, k0)
    for sign in (1, -1):
        for d_in, d in zip(coarse[:-1].tolist(), coarse[1:].tolist(), strict=True):
            fit_lag(k0 + sign * d, k0 + sign * d_in)
    grid = k_max + np.r_[-coarse[:0:-1], coarse]  # the first pass's lags, as indices into ``cost``
    if not one_valley(cost[grid], min_depth):
        return None, centres
    best_i = int(np.argmin(cost[grid]))
    b, lo, hi = (int(grid[i]) for i in (best_i, best_i - 1, best_i + 1))  # one_valley: the least lies inside
    for i in (*range(b + 1, hi), *range(b - 1, lo, -1)):  # the lags between, outwards from the least
        fit_lag(i + k0 - k_max, (i - 1 if i > b else i + 1) + k0 - k_max)
    lag = _parabolic_minimum_s(cost, k_max, fs_hz)
    return (None if lag is None else lag + k0 / fs_hz), centres


def one_valley(cost: np.ndarray, min_depth: float) -> bool:
    """Whether a profile ``cost`` (L,) over candidate lags has one clear minimum: finite, and the lags whose cost lies
    within ``min_depth`` (>= 1) times the least form one run that reaches neither end of the range. Two such runs
    are two hypotheses, not a measurement; one reaching an end may continue beyond the range searched."""
    if not np.isfinite(cost).all():
        return False
    low = np.flatnonzero(cost <= min_depth * cost.min())
    return bool(low.size and low[0] > 0 and low[-1] < cost.size - 1 and low.size == low[-1] - low[0] + 1)


def _parabolic_minimum_s(cost: np.ndarray, k_max: int, fs_hz: float) -> float | None:
    """The lag [s] of an interior minimum of ``cost`` over lags ``-k_max..k_max`` samples (NaN: a lag not evaluated)
    that stands clearly below the ends of the search range (noise and model misfit leave a floor under the whole
    curve, so compare depths, not ratios to the median), refined by a parabola through the three best lags. None
    without one."""
    if np.isnan(cost).all():
        return None
    b = int(np.nanargmin(cost))
    if b == 0 or b == cost.size - 1 or not np.isfinite(cost[[0, -1, b - 1, b, b + 1]]).all() \
            or 0.5 * (cost[0] + cost[-1]) < 1.2 * cost[b]:
        return None
    den = cost[b - 1] - 2 * cost[b] + cost[b + 1]
    frac = 0.5 * (cost[b - 1] - cost[b + 1]) / den if den > 0 else 0.0
    return float((b - k_max + frac) / fs_hz)


def joint_plane_frames(centres: JointCentres, j1: np.ndarray, j2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane x axes for Eq. 7. Instead of Seel's arbitrary ``c`` (which leaves an unknown constant offset), x_i
    points DISTALLY along each segment: thigh sensor -> knee (``-o1``), knee -> shank sensor (``+o2``), projected
    onto the joint plane. With lateral sensors these are the segments' long axes, so 0 deg = straight knee. Falls
    back to ``c = [1,0,0]`` (Seel's choice) when the joint centre lies too close to the axis."""
    xs = []
    for o, j, sign in ((centres.o1, j1, -1.0), (centres.o2, j2, 1.0)):
        v = sign * (o - (o @ j) * j)
        if centres.absolute and np.linalg.norm(v) > _EPS:
            xs.append(v / np.linalg.norm(v))
        else:
            c = np.array([1.0, 0.0, 0.0]) if abs(j[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
            x = np.cross(j, c)
            xs.append(x / np.linalg.norm(x))
    return xs[0], xs[1]


def gamma_apply(g: np.ndarray, gd: np.ndarray, o: np.ndarray) -> np.ndarray:
    """Gamma_g(o) = g x (g x o) + gdot x o = g (g.o) - o |g|^2 + gdot x o, for one o and all samples."""
    return g * (g @ o)[:, None] - np.einsum("ij,ij->i", g, g)[:, None] * o[None, :] + cross_rows(gd, o)


def accelerometer_angle_deg(a1: np.ndarray, g1: np.ndarray, gd1: np.ndarray, a2: np.ndarray, g2: np.ndarray,
                            gd2: np.ndarray, j1: np.ndarray, j2: np.ndarray, centres: JointCentres) -> np.ndarray:
    """Knee flexion from accelerometers: lever-arm correction (Seel Eq. 6) then the signed angle between the two
    corrected accelerations in the joint plane (Eq. 7). Both equal the knee-centre acceleration in each segment's
    frame, so angle_in_shank - angle_in_thigh = thigh rotation - shank rotation about j = flexion (module sign
    convention; frames x_i from :func:`joint_plane_frames`, y_i = j_i x x_i)."""
    x1, x2 = joint_plane_frames(centres, j1, j2)
    y1, y2 = np.cross(j1, x1), np.cross(j2, x2)
    at1 = a1 - gamma_apply(g1, gd1, centres.o1)
    at2 = a2 - gamma_apply(g2, gd2, centres.o2)
    ang1 = np.arctan2(at1 @ y1, at1 @ x1)
    ang2 = np.arctan2(at2 @ y2, at2 @ x2)
    z = np.exp(1j * (ang2 - ang1))
    # unwrapped around the circular mean so the angle never jumps by 360 deg whatever the frames' offset
    ok = np.isfinite(z)
    centre = float(np.angle(np.mean(z[ok]))) if ok.any() else 0.0
    return np.rad2deg(centre + np.angle(z * np.exp(-1j * centre)))
