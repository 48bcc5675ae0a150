"""Every tunable of the pipeline, as a typed tree of frozen dataclasses with named presets (after mobgap's
``PredefinedParameters``).

One dataclass per stage; :class:`PipelineParams` holds one of each. :data:`PRESETS` names the tree per activity
(``process_session(..., params=None)`` uses the activity's preset; ``unknown`` starts from ``walking``). Both presets
hold the same values: the activities differ in which stages their code path reads (``running`` vs ``fusion``), not
in the numbers. A variant is ``dataclasses.replace(WALKING, go=replace(WALKING.go, cutoff_hz=15.0))``.

Units are part of the field names; each field says why it has its value.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class PrepareParams:
    """Units, common grid and gaps (:mod:`pipeline.prepare`)."""

    gap_factor: float = 1.75
    """A step longer than this many nominal sample periods is a gap: BLE jitter stays below, one lost sample not."""
    max_bridge_s: float = 0.15
    """Longest gap bridged by the cubic [s]: one or two lost BLE packets, shorter than swing flexion (~250 ms), so
    the cubic still sees both sides of any knee event. Longer gaps are masked."""
    noted_bridge_s: float = 0.05
    """Bridged gaps longer than this [s] get a quality note on the strides they touch, and are filled from the
    neighbouring strides where the signal around them is periodic (:func:`pipeline.prepare.periodic_fill`): on the
    swing-flexion rise a cubic through 0.12 s moved the peak by p95 3.6 deg (max 5), the warped neighbouring strides
    by p95 0.8 (max 1.7; tune seeds 0-2, holes in every third stride). The cubic stays where they do not fit."""
    periodic_bridge_s: float = 0.8
    """Longest gap [s] filled from the neighbouring strides (:func:`pipeline.prepare.periodic_fill`) when the
    sensor's signal around it is periodic. Below the shortest walking stride (~0.9 s at a fast 130 steps/min): a
    stride's two heel strikes are never both inside one hole, so every filled stride keeps a measured event on this
    sensor, and the stride exists in the data even where its shape is the neighbours' (those strides stay out of
    trends: ``QualityParams.trusted_fill_s``). Five lost 20-sample packets at 128 Hz (0.79 s), the bursts of bursty
    BLE loss, fit; longer gaps are masked. Tune seeds of the sweep, 0.5 -> 0.9 s: coverage at 3 / 5 / 10 % bursty
    loss 0.91 / 0.86 / 0.71 -> 0.94 / 0.94 / 0.81, trend strides' peak LoA unchanged."""
    one_sided_fill_s: float = 0.5
    """Longest gap [s] filled from one side's strides alone (a bout's first or last stride, gait on one side of the
    hole only). Half the shortest walking stride, as ``QualityParams.trusted_fill_s``: a longer hole at a bout's edge
    may hold the bout's end, and the template would write gait into the standing or turning after it (tune seeds,
    10-sample packets at 3 % loss: the trace outside gait 1.3 -> 2.1 deg RMSE with one-sided fills up to 0.8 s)."""
    periodic_period_s: tuple[float, float] = (0.5, 2.5)
    """Search range of the stride period [s] for the periodic fill (running ~0.6, very slow walking ~2.5)."""
    periodic_context_s: float = 0.8
    """Data [s] on either side of the hole compared with the same data one period earlier/later."""
    periodic_search_hz: float = 50.0
    """Rate [Hz] of the fill's period search (every k-th lag and context sample; the template's edge shifts then
    align it to the sample and below): gait rates carry little above 10 Hz, so their correlation changes by ~0.01
    between neighbouring 20 ms lags, and the search over 0.5-2.5 s of lags at the full rate was most of a lossy
    session's preparation."""
    periodic_edge_s: float = 0.25
    """Data [s] at each edge of a hole aligned on its own with the template stride: a quarter of a stride holds a
    gait event's shape (a swing peak or a heel strike) to align on, and stays within the stride the hole is in."""
    periodic_max_warp: float = 0.08
    """Largest shift of the template at a hole's edge, as a share of the period: consecutive strides differ in
    duration by 2-3 % (CV) in steady walking (Hausdorff 2005), more at turns and in patients."""
    periodic_min_corr: float = 0.8
    """Least correlation between the hole's context and its one-period-shifted copy: gait repeats with r > 0.9
    from stride to stride; standing noise, turns and transitions do not, and their holes stay masked."""
    saturation_run: int = 3
    """A gyro axis pinned at its extreme for this many samples in a row counts as saturated."""
    saturation_min_dps: float = 200.0
    """Only extremes above this rate [deg/s] can be a clipped sensor (gait peaks reach 300-1000 deg/s)."""
    saturation_tol: float = 1e-4
    """A sample is pinned at its axis' extreme within this share of it: a clipped sensor repeats its full-scale code
    (one LSB of a 16-bit +-2000 deg/s gyro is 3e-5 of it). A smooth peak sampled at 200 Hz keeps three samples
    within 0.1 % of its top (the earlier tolerance: an independent simulator's unclipped running strides were marked
    ``saturation``), but within 0.01 % only below ~0.5 Hz, which no gait peak is."""


@dataclass(frozen=True)
class AxesParams:
    """Joint axes (Seel Eq. 2), joint centres (Eq. 5) and accelerometer angle (Eq. 6-7) (:mod:`pipeline.axes`)."""

    fit_cutoff_hz: float = 10.0
    """Gyro/acc low-pass [Hz] for the axis and centre fits and the accelerometer angle: keeps gait (< 6 Hz),
    drops sensor noise and impact ringing."""
    min_gait_strides: int = 3
    """Fewest gait strides (:func:`pipeline.bilateral.gait_strides`) that anchor a leg's knee axes, their signs and
    its zero; with fewer the leg shows no angle and keeps no stride (``pipeline.session``). A turn on the spot
    gives 1-2 (on an independent simulator's crutch gait whose own steps gave no strides, 1-2 per leg from its
    turns anchored a trace that read a 30 deg swing as -14 deg); a single walk of 5 steps gives 3."""
    sign_min_strides: int = 2
    """Whole strides each sign of both axes must find for :func:`pipeline.walking.orient_on_gait` to compare them: the
    given sign of a walker's 4 s cycles finds two (an independent simulator), and a sign that finds none is not
    judged (a step test alone)."""
    sign_margin_deg: float = 15.0
    """How much more one-sidedly the knee must flex under the other sign of both axes for them to be turned
    (:func:`pipeline.walking.orient_on_gait`, medians of :func:`pipeline.axes.knee_excursion_deg`) [deg]. Each sign
    is judged on its own strides: in this repository's walking the right sign reads +19 .. +22 and the wrong one, where
    it finds strides at all, +2 .. +5 (16-20 apart); in an independent simulator's step-to gait the two lie 48-79
    apart, the wrong one reading the negated knee. Less is a near tie, in which neither sign's strides show a knee
    that flexes away from extension."""
    fit_margin_s: float = 0.1
    """Centre-fit samples stay this far [s] from a masked gap: filters and Eq. 1 differences are unreliable there."""
    max_fit_samples: int = 1000
    """Sample budget of one fit: bounds the cost whatever the session length."""
    fit_chunks: int = 20
    """Equal time chunks the budget is spread over, so the fit set spans the whole session."""
    centre_fit_hz: float = 100.0
    """Candidate rate [Hz] of the joint-centre fit's samples (:func:`pipeline.axes.centre_fit_step`): every sample up
    to 100 Hz, every other at 200 Hz, so the budget covers the same stretch of gait at any rate."""
    n_restarts: int = 2
    """Seeded restarts of the axis fit besides the principal-axis start (Eq. 2 has local minima)."""
    fit_lag: bool = True
    """Refine the hinge axes together with a thigh-shank clock lag (:class:`pipeline.axes._AxisLagProblem`) before
    the clock is corrected: with 3-D hip motion the axes alone absorbed part of a lag, and the hinge cue then read
    ~1/3 of it (21 ms as 7; sweep axis ``joint_3d``)."""
    axis_level: bool = True
    """Turn each segment's knee axis towards the plane perpendicular to its mean specific force
    (:func:`pipeline.axes.level_directions`), to within ``level_lean_deg``: the flexion axis of a knee that also
    rotates about the tibia's long axis, instead of the oblique axis of Seel's hinge fit (sweep axis ``joint_3d``)."""
    level_lean_deg: float = 4.0
    """Lean [deg] out of that plane left to a fitted axis: the plane's own uncertainty. A session's mean specific
    force leans off the true vertical by what its accelerometer's residual offset tilts it (0.05 g: 3 deg) and by
    the mean hip ab/adduction and pelvic obliquity (1-2 deg); a hinge axis leaning less than that is no evidence of
    axial rotation and is kept. Tune seeds: 0 deg made accelerometer offsets of 0.5 and 1 m/s^2 misses (peak LoA
    -3.3 .. 1.7 -> -3.5 .. 1.9, -4.0 .. 2.6 -> -5.9 .. 4.0) and shifted 5-10 g rows by 0.1-0.4 deg; 4 deg leaves
    them as they were and keeps the gains on 3-D knees."""
    max_level_lean_deg: float = 40.0
    """A hinge leaning further than this [deg] out of that plane is not a knee turning as it flexes (8-15 deg per
    segment at typical coupling, 15-30 at twice it, on the simulator's ``joint_3d`` chain) but a plane that is not
    the body's: sensors left lying off the body for part of a session move its mean specific force to wherever
    they lay (an independent simulator: 48-75 deg, and levelling towards it put the strides' peaks 25 deg low). The
    hinge axes are kept as fitted then."""
    n_centre_starts: int = 4
    """Seeded starts of the centre fit besides the near-zero one (Eq. 5 has mirrored minima)."""
    max_lever_m: float = 0.6
    """A sensor further than this [m] from the knee is not on the thigh or shank: no lever-arm correction then (the
    longest adult thighs and shanks are ~0.5-0.55 m; a thigh sensor may sit anywhere up to the hip)."""
    centre_reg: float = 0.05
    """Pull of the centres towards 0 [m/s^2 per m, per sample]: negligible against real misfit, fixes the flat
    valley of Eq. 5 along the axis."""
    centre_bias_prior_mps2: float = 0.0
    """SD [m/s^2] of the zero-mean prior on each accelerometer axis's constant bias, fitted with the joint centres
    as a nuisance parameter (:func:`pipeline.axes.fit_joint_centres`) in the directions the session makes observable
    (:func:`pipeline.axes.observable_bias_basis`); 0 fits no bias. Off: at 0.3 (~0.03 g, the zero-g offset class of
    consumer MEMS accelerometers) a 12-minute session processed in blocks matches itself again (median peak
    difference 0.09-0.35 deg, 0.5 allowed) and lever arms x2 improve (sweep tune seeds, peak LoA -3.8 .. 1.4 ->
    -3.0 .. 1.1), but 128 Hz sessions (bursty-loss axis: 3 % loss LoA -3.0 .. 1.4 -> -3.6 .. 1.3), fast walking
    (accuracy tune seeds, bias -0.90 -> -1.12 deg) and 40 Hz (report seeds, LoA -2.5 .. 3.1 -> -2.3 .. 3.6) get
    worse."""
    centre_bias_sd_ratio: float = 0.5
    """A bias direction is fitted only where its posterior SD (cluster-robust information plus the prior) is below
    this share of the prior SD, i.e. where the data carry at least (1/0.5^2 - 1) = 3 times the prior's information;
    the rest stays at 0 instead of following the fit's misfit."""
    centre_offset_prior_mps2: float = 0.3
    """SD [m/s^2] of the zero-mean prior on a constant offset of the Eq. 5 residual fitted with the biases: the two
    accelerometers' sensitivity mismatch (consumer MEMS: +-2 % each, ~0.28 m/s^2 at 1 g for the pair)."""
    centre_bias_check_level: float = 0.99
    """The fitted biases and offset are dropped (the centres kept from the bias-free fit) when their squared norm over
    the prior variances exceeds this quantile of chi-square with as many degrees of freedom as fitted unknowns:
    values that large are not what the priors describe but other misfit absorbed by those terms."""


@dataclass(frozen=True)
class SyncParams:
    """Thigh/shank clock offset and drift from the hinge constraint (:mod:`pipeline.sync`)."""

    window_s: float = 40.0
    """One lag estimate per window [s]: long enough for a stable minimum, short against crystal drift. A leg of two
    to three windows is cut into three shorter ones, so that its drift is seen."""
    max_drift: float = 500e-6
    """Largest rate error [s/s] between a thigh's and a shank's clock that the stride timing accepts after the clock
    model (:func:`pipeline.sync.stride_clock_runaway`): crystals are specified to +-20-50 ppm and move by tens more
    with temperature and age, so two of them differ by up to ~200 ppm; a leg whose remaining drift lies beyond 500
    ppm was not brought onto one clock, and its strides stay out of trends (``clock_disagreement``). Clocks without
    a crystal (the calibrated RC oscillators of BLE chips, +-250-500 ppm each) drift apart faster; the window lags
    follow them up to :attr:`max_line_drift`."""
    crystal_drift: float = 200e-6
    """Largest rate error [s/s] between two crystal clocks (+-20-50 ppm each, tens more with temperature and age).
    A leg whose clocks nothing corrected (no window line) and whose stride timing shows a drift wholly beyond it
    has a timing that no correction covers (300 ppm: +-14 ms at the ends of 90 s): ``clock_disagreement``."""
    agree_s: float = 0.006
    """The window lags must agree with the fitted line within this [s], or no correction is applied."""
    window_lag_floor_s: float = 0.0007
    """Smallest standard error [s] a hinge window's lag is weighted with in the line fit: the cost curve's error
    (:func:`pipeline.axes.sync_lag_estimate`) sees the rates' noise, not what scatters window lags by ~0.7 ms around
    their line on clean data (gait-locked misfit, a window's place in time under drift; tune seeds). 0.3 ms gave the
    same offsets on 60 legs at 10 % packet loss."""
    stride_cue_window_s: tuple[float, float] = (0.35, 0.15)
    """Where a stride's thigh swing peak is looked for, before and after the shank's mid-swing peak [s]
    (:func:`pipeline.sync.stride_clock_runaway`): it leads by ~0.12 s in simulated walking."""
    stride_cue_min_strides: int = 20
    """Fewest strides the stride-timing check of the clock runs on."""
    stride_cue_min_span_s: float = 30.0
    """Shortest span [s] of those strides: over less, 500 ppm moves the stride timing by less than its noise."""
    max_lag_s: float = 0.06
    """Search range of the lag [s]: larger offsets are not a clock error between two BLE sensors."""
    wide_max_lag_s: float = 0.15
    """Search range of the lag [s] where none is found within ``max_lag_s`` (:func:`pipeline.sync.clock_model`):
    stamps taken on the phone as packets arrive carry a BLE connection interval (7.5-100 ms) and the radio's
    buffering. Far inside a stride (the hinge cue's next minimum lies a whole cycle away)."""
    wide_from_share: float = 0.75
    """A line found beyond this share of ``max_lag_s`` is searched over ``wide_max_lag_s`` too (a 75 ms offset read
    as 67 ms, a 90 ms one as 54 ms on the simulator: the narrow windows followed it part of the way out)."""
    centre_depth: float = 2.5
    """How clear a joint-centre lag's minimum must be (:func:`pipeline.axes.one_valley`, >= 1): the lags whose Eq. 5
    cost lies within this many times the least form one valley that reaches neither end of the search range; else
    the window reads no lag. The sweep's tune seeds and running scans of this simulator (425 windows, centres
    refitted at each lag): of the windows whose least cost lay within 5 ms of the true lag, 382 of 387 pass (twice
    the least: 384, three times: 380); of those more than 10 ms off (a thigh sensor 50 cm from the knee, shocks that
    leave the sensor faster, long runs with 3-D knees), 1 of 13 (twice: 3, three times: 0)."""
    centre_lag_step_s: float = 0.01
    """Spacing [s] of the joint-centre lag profile's first pass (:func:`pipeline.axes.estimate_centre_lag_s`); the
    lags between its least and that one's two neighbours are fitted after, to the sample. Each lag is a
    Levenberg-Marquardt fit of the centres, and the lags within ``max_lag_s`` grow with the rate (121 at 1000 Hz).
    The profile is one smooth bowl over the range (its second valleys, where a window has them, lie 30-60 ms away),
    so its least on a 10 ms grid lies next to the true one: on 2-minute walks at 200, 500 and 1000 Hz and runs at
    200 Hz (seeds 0-1) every lag read equals the one read with every lag fitted to 0.1 ms. Below 150 Hz the pass
    is one sample: every lag is fitted."""
    wide_max_se_s: float = 0.004
    """Largest standard error [s] of a hinge window's lag the wide search takes: over +-0.15 s the shallow cost curve
    of a window without a walk (a stair flight, exercises) has false minima 50 ms out (standard errors 5.5-8 ms on
    the simulator's tune seeds); windows of walking read 1.5-3.7 ms."""
    wide_min_windows: int = 3
    """Windows that must speak in the wide search (the narrow one takes two)."""
    scattered_max_lag_s: float = 0.015
    """Where the wide search's window lags scatter beyond ``agree_s`` but every one lies beyond this [s] on the same
    side, the leg's timing is unknown (``clock_disagreement``: its strides stay out of trends); 15 ms move the swing
    peak by ~7 deg. Windows of exercises without a walk scatter on both sides and leave the leg as it was."""
    restamp_max_lag_s: float = 0.25
    """Widest lag [s] searched on a whole leg re-stamped by the stride timing's drift (a clock without a crystal,
    :func:`pipeline.sync.synchronised_leg`): a quarter of a slow stride, so that the hinge cue's cost of a periodic
    gait signal has no second minimum a stride away in the range."""

    @property
    def max_line_drift(self) -> float:
        """Steepest line [s/s] of the window lags that is applied: a drift that moves the lag across one window by
        twice the search range (3000 ppm in 40 s windows) smears that window's cost minimum beyond what the search
        sees. Steeper lines leave the leg uncorrected and out of trends (``clock_disagreement``)."""
        return 2 * self.max_lag_s / self.window_s
    min_shift_samples: float = 0.25
    """A correction smaller than this share of a sample period is not applied (re-preparing costs time)."""
    max_centre_windows: int = 8
    """Most windows the joint-centre cue is evaluated on, spread evenly over the session: each costs one or two
    Levenberg-Marquardt fits of the centres per candidate lag (13 at 100 Hz), and an offset with a drift needs only
    a few agreeing points, so the cost of a long recording without turns stays that of eight windows."""
    check_centre_windows: int = 3
    """Windows the joint-centre cue checks a hinge-cue line on (:func:`pipeline.sync.clock_model`), each searched
    from the middle window's lag, once the middle window alone differed from it by more than ``agree_s`` (where the
    cues agree, one window per leg). Where the two lines differ by more than ``agree_s`` at mid-session, the joint
    centre's is applied. A knee whose tibia turns as it flexes without the hinge fit leaning reads 10-25 ms into the
    hinge cue (an independent simulator: 6 of 80 legs beyond 10 ms, levels off by up to 24 deg; this simulator's
    running with 3-D knees: 30 ms on exact clocks). Of 27 disagreeing legs (walking with the hinge-lean test off,
    running; 3-D knees, tune seeds), the centre's line lies within 5 ms of the truth on all 27, the hinge's on none;
    a refit of the centres on the leg re-stamped by each line, keeping the better Eq. 5 fit, picks the hinge's on 8
    (its robust scale leaves out the heel strikes' large residuals, where the timing shows). Where the knee is an
    exact hinge the centre's line can be the wrong one: the simulator's planar knee at 200 Hz, one leg of ten, -16
    ms against a true -4.6 (ROM LoA -0.5 .. 0.2 -> -1.3 .. 1.5 deg); no real knee is one (Eq. 2 residual 25 deg/s on
    the biomechZoo trial, 0.1-0.3 on the simulator's planar knees). The centre cue alone, used wherever the hinge
    speaks, is less accurate (lever arms x2 on the sweep's tune seeds). Three windows give the offset and its drift
    and can disagree with a line (where they make none, or one that runs away faster than ``crystal_drift`` while
    the hinge's does not, :func:`pipeline.sync._checked_by_centre` asks whether one of them reads the hinge line,
    else the timing is unknown), at under half the cost of ``max_centre_windows``."""
    shock_g: float = 1.0
    """Acceleration above the fit band [g] (a sensor's raw acceleration minus its ``AxesParams.fit_cutoff_hz``
    low-pass, :func:`pipeline.sync.shock_mask`) marking a shock whose samples the joint-centre cue leaves out: 5 and
    10 g heel strikes moved its lag by -3.1 +- 4.6 and -7.5 +- 5.4 ms (sweep tune seeds, up to 16 ms), -0.1 +- 1.3 and
    -0.2 +- 1.3 ms without those samples."""
    shock_s: float = 0.06
    """Samples left out on either side of a shock sample [s]: the simulated shock rings for ~50 ms."""
    short_window_s: float = 4.0
    """Shortest half [s] of a leg too short for two ``window_s`` windows that the joint-centre cue is run on: a 4 s
    half holds three to four strides of normal walking, so a 10 m walk test (~10 s) is covered; on the real
    biomechZoo trial (10 s) the two halves agree within 2 ms."""
    short_min_lag_s: float = 0.004
    """A lag of a leg too short for two ``window_s`` windows is applied only above this [s]: on halves of a few
    strides the joint-centre cue reads up to 3.7 ms on the hardware-synchronised biomechZoo trial and up to 6.8 ms on
    simulated 10-20 s sessions with exact clocks (tune seeds; 40-60 s: within 2.2 ms), while 4 ms move the swing
    peak by ~0.7 deg."""


@dataclass(frozen=True)
class PhaseParams:
    """Gait events from the shank sagittal rate (:mod:`pipeline.phases`, Allseits et al. 2018)."""

    lobe_cutoff_hz: float = 4.0
    """Smoothing [Hz] for swing lobes and mid-swing peaks: one lobe per swing."""
    event_cutoff_hz: float = 15.0
    """Light smoothing [Hz] for the toe-off and heel-strike minima (keeps their timing)."""
    min_peak_dps: float = 50.0
    """Smallest mid-swing peak [deg/s]: slow walking reaches ~150; standing sway stays far below."""
    rel_peak: float = 0.35
    """A lobe reaching this share of the session's typical swing peak, the upper quartile of its lobes, is a swing
    (turns, shuffles and the tibia's roll over the foot in mid-stance are lower)."""
    rel_peak_local: float = 0.6
    """So is a lobe reaching this share of the largest lobe near it (``rel_window_lobes``): a slow bout in a brisk
    session. Consecutive swings of steady gait differ by a few %; a step-up's trailing-leg lobes are half the
    leading leg's and the tibia's roll a third of the swing."""
    rel_window_lobes: int = 4
    """Neighbours on either side (and within ``max_period_s``) that a lobe is compared with: with up to one stance
    lobe per stride, 4 hold the swings of two strides each side."""
    stance_neg_dps: float = 10.0
    """The smoothed rate must drop below minus this [deg/s] between two swings (a real stance)."""
    min_period_s: float = 0.5
    """Shortest plausible stride [s] for walking bouts."""
    max_period_s: float = 3.0
    """Longest plausible stride [s] (very slow walking). Step-to gait with crutches or a walker runs 2-5 s a cycle (two
    steps, two pauses of double support), and its longer cycles are lost (a quarter of an independent simulator's).
    Longer strides are not taken: at 4.5 s the step-ups of a step test become strides (59 false on the sweep's
    step-test row after a walk), and at 4.5 s between neighbours alike in period, sit-to-stand repetitions 4-5 s
    apart chain into bouts whose zero-angle updates fall in sitting (the trace there read down to -15 deg on 3 of 12
    legs of another independent simulator)."""
    period_tol: float = 0.35
    """A stride off its neighbours' median period by more than this share breaks the bout."""
    min_bout_peaks: int = 3
    """Shortest bout [swing peaks] that produces strides (isolated steps are not gait)."""
    search_s: float = 0.3
    """Toe-off search window before a lobe start [s]."""
    stance_pct_range: tuple[float, float] = (30.0, 92.0)
    """Plausible stance share of a stride [%]; outside it the events are wrong. 60-65 % in walking at ordinary
    speed, more as it slows; in step-to gait a leg swings 0.45-0.7 s of a 2-3 s cycle (75-85 %), and the swing lobe
    the events come from is a little shorter than the swing: an independent simulator's step-to strides read
    73-90 %, a third of them above 85 %. The ``RUNNING`` preset keeps 85 %."""
    min_swing_thigh_deg: float = 0.0
    """Least forward turn of the thigh over a stride's swing [deg] for the stride to be a step
    (:mod:`pipeline.stepping`). Zero is the physical bound: a foot that moves forward turns its thigh forward. Gait
    +4 .. +52 on this repository's simulator (one stride at a bout's end -3), +3 .. +48 on an independent one;
    marching in place -35 .. -39, side steps -2 .. -6. Below it, and below ``min_contact_thigh_deg``, the stride is
    dropped."""
    min_contact_thigh_deg: float = 10.0
    """Least the thigh stands forward at the next heel strike of its most extended within the stride [deg]
    (:func:`pipeline.stepping.thigh_landing_deg`), which spares a stride whose thigh turned back over the swing: in
    running the detected toe-off lies in mid-swing and the thigh retracts before the strike (an independent
    simulator's running strides that turned back landed 16-50 deg forward). A lowered leg lands where it stood:
    marching 0 .. +3 deg on two simulators. About half-way between."""
    to_delay_s: float = 0.04
    """Toe-off after the shank minimum [s]: measured against the Tan et al. 2022 force plate."""
    hs_delay_s: float = 0.02
    """Heel strike after the smoothed zero crossing [s] when no impact stands out (Tan et al. 2022: 10-30 ms)."""
    impact_window_s: tuple[float, float] = (-0.03, 0.12)
    """Window around the zero crossing [s] searched for the heel-strike impact."""
    impact_prominence: float = 3.0
    """An impact stands out when its jump exceeds this multiple of the window's median jump."""
    level_band_deg: float = 20.0
    """Knee flexion above the stride's minimum [deg] still counted as near extension (:mod:`pipeline.level_walking`):
    the loading-response flexion of level walking, 10-25 deg from slow to fast (Lelas et al. 2003)."""
    level_min_share: float = 0.5
    """Least share of a walking stride near extension for it to be level gait: real walking 0.59-0.68, the
    simulator's walking patterns 0.61-0.80, its stair flights 0.29-0.41 (:mod:`pipeline.level_walking`)."""
    stance_above_swing_deg: float = 10.0
    """A walking stride whose knee flexes more in stance than at its swing peak by more than this [deg] is a step
    down, not level gait (:func:`pipeline.level_walking.stance_above_swing`): level gait 0.0 on every stride of
    four sources (README), an independent simulator's step-downs 37-39. The margin spares a shuffle whose swing peak
    is as small as its loading response."""
    gap_guard_s: float = 0.15
    """No stride whose heel strikes lie closer than this [s] to a masked sample: an event searched up to a hole
    (heel strike up to ``impact_window_s[1]`` after the swing lobe's end) may have fallen inside it, and the nearest
    measured point taken instead would be early."""


@dataclass(frozen=True)
class AssignmentParams:
    """Sensor-label checks (:mod:`pipeline.assignment`)."""

    rate_percentile: float = 98.0
    """Percentile of the gyro norm taken as the segment's swing rate (gait fills more than 2 % of any session that
    has strides)."""
    swap_ratio: float = 0.8
    """Shank over thigh swing rate below this: the labels are swapped. In gait the shank swings ~2-3x faster than
    the thigh (swing peaks ~350 vs ~150 deg/s); measured 1.9-2.7 over the simulator's robustness axes and 2.4 on the
    real biomechZoo trial, 0.3-0.45 with the labels swapped."""
    keep_ratio: float = 1.25
    """Above this ratio the labelled order is confirmed; in between (no gait) nothing is decided."""
    centre_suspect_mps2: float = 0.25
    """A joint-centre fit residual (Seel Eq. 5) above this [m/s^2] makes the thigh pairing between the legs worth
    testing: 0.04-0.22 with right labels on the simulator (up to 0.55 with a thigh sensor 50 cm from the knee),
    0.38-0.92 with the thighs swapped; 0.64-0.65 with right labels on the real biomechZoo trial, so there every
    session is tested (the decision itself is relative: :func:`pipeline.assignment.swapped_pairing_better`)."""
    centre_height_margin_m: float = 0.05
    """How far above the knee centre the thigh sensor must lie, less how far the shank sensor does, for the centres
    to say which sensor is which [m] (:func:`pipeline.assignment.segments_by_centre`): +0.25 .. +0.41 with the right
    order on the simulator (walking, crouch, running, sitting between bouts), +0.25 / +0.30 on the real biomechZoo
    trial; -0.29 .. -0.38 where the swing rates had exchanged a right order (high knees between walks)."""
    pairing_gain: float = 0.5
    """The swapped thigh pairing is taken when its summed residual is below this share of the labelled one."""
    shift_window: float = 0.3
    """Share of each stride from heel strike over which the thigh's weight-shift rotation is averaged
    (:func:`pipeline.assignment.weight_shift_dps`): loading response and early mid-stance, while the weight moves
    over the stance foot (the lateral excursion of the centre of mass peaks at mid-stance, ~30 % of the cycle)."""
    shift_min_dps: float = 2.0
    """Weight-shift rate [deg/s] each leg must show in both figures of :func:`pipeline.assignment.weight_shift_dps`,
    in the other leg's sense, before the sides are in doubt. The real biomechZoo trial: left +14 / +7.7, right -8.0 /
    -3.8. The simulator (tune seeds 0-19): with typical pelvis and hip motion the first figure is mirrored on every
    session (2.5-15), the second on about half (-2 .. 8 on a left leg), so about half of the swaps are caught and no
    session with right labels was flagged on any tested configuration. A planar walker reads 0.0-0.4 in both; a
    thigh skin turning 10 deg with the knee, or a gyro bias of 10 deg/s that no rest removed, moves the first figure
    by 3-16 and the second by at most 1.7, which is why both must agree."""
    shift_min_strides: int = 5
    """Whole strides a leg needs for its weight shift to be read (a median over strides)."""


@dataclass(frozen=True)
class MountingParams:
    """Mounting-change check (:mod:`pipeline.mounting`): the hinge refitted per time window, before against after."""

    window_s: float = 15.0
    """Length of each window [s]: a walking bout or two, enough samples for a stable hinge (the session's own fit
    takes at most ``AxesParams.max_fit_samples`` too)."""
    moving_dps: float = 60.0
    """A sample counts as moving when the shank turns faster than this [deg/s] (swing peaks: 150 when shuffling,
    350-450 when walking)."""
    min_moving_s: float = 3.0
    """Moving time a window needs to be fitted [s]: about ten swings."""
    max_fit_samples: int = 300
    """Samples per window fit (the most dynamic, spread over ``fit_chunks`` parts of the window)."""
    fit_chunks: int = 6
    """Parts of each window the fit samples are spread over (:func:`pipeline.axes.select_fit_samples`)."""
    min_windows: int = 2
    """Fitted windows needed on each side of a split point."""
    thigh_deg: float = 35.0
    """A change of the thigh's axis beyond this [deg] is a remount. The thigh's fitted hinge moves with the hip's 3-D
    motion: on the simulator (tune seeds 0-3, sessions of 90 and 240 s) the before/after means moved by up to 12 deg
    with typical 3-D hip and knee motion (walking, stairs, jumps), 19 at changing paces, 29 at twice the typical
    motion with a varus knee; a thigh turned by 60 deg about a random axis moved them by 17-60 (8 of 12 caught)."""
    principal_thigh_deg: float = 8.0
    """``thigh_deg`` where the thigh's axis is its principal rotation axis per window (running,
    ``RunningParams.thigh_axis``): that axis does not wander with the hip's and knee's 3-D motion as the refitted hinge
    does (150 s runs without a remount: 0-0.3 deg on this repository's simulator with 3-D hip and knee and on an
    independent one, where the refitted hinge read 4-21 and 48-53 deg), and a turn of the sensor moves it by up to
    the turn's angle (30 deg about a random axis: 12-30; 15 deg: 6-15). Below ~8 deg a turn moves the knee rate by
    1 % at most."""
    shank_deg: float = 14.0
    """A change of the shank's axis beyond this [deg] is a remount. The same sessions: up to 6.6 deg with typical
    3-D motion, 12.5 at twice it with a varus knee; a shank turned by 30 deg about a random axis: 8-28 deg (6 of 12
    caught in 90 s, more in longer sessions)."""
    level_step_deg: float = 5.0
    """A step of the leg's level beyond this [deg], seen alike in quiet standing and in the walking strides, is a
    remount (:func:`pipeline.mounting.level_step`). Standing alone steps when a patient stands differently (a few deg
    between stands), the strides alone when the gait changes (their GO zero sits at the knee's minimum before swing);
    a sensor turned on its segment moves both by the same amount. On the simulator (tune seeds 0-4, 90 s) both
    levels stay within 2 deg over a session without a remount; a shank turned by 15 deg about a random axis steps
    them by 2-13 deg, a thigh turned by 30 deg by 4-28."""
    level_agree_deg: float = 2.5
    """The two steps (standing, strides) must agree within this [deg] and share their sign."""
    level_min_strides: int = 6
    """Strides with a mid-stance level needed on each side of a split point."""


@dataclass(frozen=True)
class WornParams:
    """Sensors not on the leg (:mod:`pipeline.worn`): handled unlike a knee, or a rest in a posture nobody walks in
    while the other leg walks."""

    handled_window_s: float = 0.5
    """Window of the hinge test's RMS values [s]: a quarter of taking a sensor off, half a stride."""
    handled_min_dps: float = 30.0
    """The faster segment's RMS rate a window needs to be judged [deg/s]: slower, noise and bias weigh too much
    (a sensor laid down gently turns at 50-90)."""
    handled_ratio: float = 0.6
    """A window whose RMS hinge residual exceeds this share of that rate turned unlike a knee. On the simulator (tune
    seeds 0-5: walking, turns, running with ringing 10 g impacts, jumps, stairs, exercises, each with twice the
    typical 3-D knee and hip motion, three times the wobble) a knee stayed above 0.5 for ``handled_min_s`` only in
    exercises with twice the 3-D motion, above 0.45 in jumps too; a sensor taken off: 0.67-0.99 (it turns partly
    about the knee axis, which a knee does too). Real Xsens walking (biomechZoo): 0.42 at most in any window."""
    handled_turned_deg: float = 30.0
    """A stretch is no handling where each segment's mean specific force over the second after it points within this
    [deg] of that over the second before (:func:`pipeline.worn._a_turn_of_the_body`):
    an independent simulator's pivot turns (137-140 deg on one foot, the tibia turning 15-20 deg against the femur)
    broke the hinge as much as a removal and cut 57-187 s of 32 legs out; a turn about the vertical leaves gravity
    where it was in both sensors, a sensor laid down or strapped back on moves it by 45-90 deg."""
    handled_min_s: float = 0.5
    """How long the residual must stay above ``handled_ratio`` [s]: a quarter of taking a sensor off; impacts and
    wobble last tens of ms."""

    min_rest_s: float = 5.0
    """Shortest rest judged [s]: a few of the other leg's strides, longer than a pause between two steps."""
    min_swings: int = 3
    """Swings of the other leg's shank within the rest that make it a walk on one leg (two could be a turn on the
    spot or shifting the weight)."""
    reach_s: float = 10.0
    """How far the stretch reaches back to the end of the leg's last stride and on to its next swing [s]: taking two
    sensors off their straps and laying them down, or putting them back on."""
    min_piece_s: float = 10.0
    """Shortest stretch between two not-worn spans (or the session's ends) processed on its own [s]: a few strides to
    learn the knee axes from; a shorter one shows nothing."""
    trusted_piece_s: float = 60.0
    """A piece of a leg whose sensors were handled that is shorter than this [s] keeps its strides out of trends
    (``sensors_handled``): too short for its own mounting check (two 15-s windows on either side of a change,
    MountingParams) to vouch for one mounting in it; on the simulator, pieces of 15-50 s around a sensor turned by
    90 deg let strides 6-17 deg off into trends."""
    after_stride_s: float = 0.2
    """Kept after that last stride's end [s]: its heel strike is found on the samples that follow it."""


@dataclass(frozen=True)
class MetricsParams:
    """Per-stride metrics (:mod:`pipeline.metrics`)."""

    loading_share: float = 0.6
    """The loading-response flexion peak is searched from heel strike over this share of stance."""


@dataclass(frozen=True)
class GoParams:
    """Gyroscope-only angle with zero-angle updates (:mod:`pipeline.estimators.go`, Allseits et al. 2018)."""

    cutoff_hz: float = 20.0
    """Low-pass [Hz] of the knee rate before integration (Allseits Sect. 2.4.1: low-order Butterworth)."""
    first_zau_lookback_s: float = 0.6
    """A bout's first update is searched this far [s] before its toe-off (no preceding mid-stance)."""
    zau_after_to_s: float = 0.05
    """The update window ends this far [s] after toe-off."""


@dataclass(frozen=True)
class CfParams:
    """Complementary filter (:mod:`pipeline.estimators.cf`, Seel et al. 2014, Rhudy Eq. 17)."""

    tau_s: float = 0.5
    """Time constant [s] of the accelerometer correction, lambda = dt / tau: shorter follows accelerometer noise on
    real data (biomechZoo), longer lets gyro bias through (simulator)."""
    restart_quiet_share: float = 0.5
    """Walking: the filter restarts after a filled hole when at least this share of the second after it is quiet
    (:func:`pipeline.estimators.cf.walking_cf`): the start value is then the accelerometer angle of gravity alone."""


@dataclass(frozen=True)
class KfParams:
    """Kalman filters (:mod:`pipeline.estimators.kf`, :mod:`pipeline.estimators.ekf`, Rhudy et al. 2024)."""

    r_deg2: float = 100.0
    """Accelerometer-angle variance R [deg^2]: only Q/R shapes the estimate, R sets the initial variance's scale."""
    filter_tau_s: float = 2.0
    """Fusion time constant [s] of the bare filter functions (the registered estimators tune their own): long
    against a stride, so within-stride accelerometer errors average out, short against gyro drift."""
    quiet_r_scale: float = 0.01
    """R is multiplied by this while the leg is quiet: the accelerometer angle then sees gravity only."""
    start_span_s: float = 1.0
    """A filter's start value (at the session's start and after every hole) explains this much [s] of accelerometer
    angle given the gyroscope's motion (:func:`pipeline.estimators.kf.start_from_measurement`): one stride or more,
    so the segment accelerations average out, short enough that the gyro's drift over it stays below a degree."""


@dataclass(frozen=True)
class TuningParams:
    """Automatic fusion time constant of the KF/EKF from the gyro's residual drift (:mod:`pipeline.tuning`)."""

    drift_tol_deg: float = 2.0
    """Drift [deg] the filter may let through before the accelerometer corrects it."""
    tau_range_s: tuple[float, float] = (0.5, 16.0)
    """Clamp of the tuned time constant [s]."""
    min_strides: int = 6
    """Fewer fully valid strides give no usable scatter: the untuned constant is used."""
    untuned_tau_s: float = 4.0
    """Time constant [s] when the leg has too few strides to tune: a few strides of averaging."""


@dataclass(frozen=True)
class FilterInputParams:
    """Per-stride de-biasing of the knee rate (:mod:`pipeline.filter_inputs`)."""

    bias_smooth_strides: int = 15
    """Running median width [strides] of the per-stride bias (also the averaging the tuning assumes)."""
    bias_outlier_mads: float = 3.0
    """Strides further than this many robust SDs from the median (gait initiation, termination) are dropped."""
    bias_min_spread_dps: float = 1.0
    """Floor [deg/s] of that outlier limit, so a very regular session keeps its strides."""


@dataclass(frozen=True)
class PostureParams:
    """Quiet postures, standing and the absolute zero (:mod:`pipeline.posture`): one definition for every consumer
    (walking policy, CF, KF, EKF)."""

    still_dps: float = 15.0
    """Both segments slower than this [deg/s]: still (sway is a few deg/s, slow walking hundreds); one sensor slower
    than this for ``quiet_min_s``: a rest for its offsets (:mod:`pipeline.rest_offset`)."""
    force_tol: float = 0.1
    """Specific force within this share of g: no segment acceleration (each accelerometer's rest offset removed
    first, :mod:`pipeline.rest_offset`)."""
    rest_offset_prior_mps2: float = 0.5
    """Prior SD [m/s^2] per axis of an accelerometer's offset (uncalibrated MEMS: 20-80 mg), fitted from the
    session's rests and removed in preparation (:mod:`pipeline.rest_offset`); 0: no accelerometer offset is fitted."""
    rest_block_sd_mps2: float = 0.1
    """Scatter [m/s^2] of one rest block's mean about the sphere |a - b| = g (sway, noise): weighs the prior against
    the data in the rest-offset fit."""
    rest_orientation_deg: float = 20.0
    """Rests within this angle [deg] of each other are one posture for the rest-offset fit: sway tilts a standing
    segment by a few degrees, postures differ by tens (sitting turns the thigh by ~90)."""
    rest_offset_warn_mps2: float = 1.0
    """An accelerometer offset of at least this [m/s^2] (0.1 g) gets a session warning: the sweep's ``sensor`` axis
    misses its targets from there (what one posture cannot show stays in)."""
    rest_offset_max_mps2: float = 3.0
    """A fitted accelerometer offset larger than this [m/s^2] (0.3 g, beyond any data sheet) is not an offset: none
    is removed. (The gyro bias needs no such cap: rests are slower than ``still_dps``, so is their median.)"""
    quiet_min_s: float = 1.0
    """Shortest quiet run [s] (and least total standing for a zero): a second of stillness outlasts the settling
    after a movement stops and averages the accelerometer noise below a degree."""
    upright_deg: float = 45.0
    """Upright: gravity within this angle [deg] of its direction during gait (:func:`pipeline.posture.
    gait_up_directions`: the thigh's mean over the strides, the shank's at the foot strikes). Sitting puts the thigh
    ~90 deg off; the shank stands within ~20 deg of vertical at a strike, walking or running."""
    up_cycles: int = 64
    """Strides, evenly spread over the session, whose foot strikes give the shank's direction during gait: bounds
    the cost whatever the session length (one strapdown pass over each)."""
    bout_margin_s: float = 1.0
    """Samples within this time [s] of a bout's first/last mid-swing are walking, not standing."""
    standing_knee_deg: float = 4.0
    """Knee flexion [deg] assumed for relaxed quiet standing (healthy adults ~2-6 deg)."""
    standing_knee_measured: bool = False
    """True when ``standing_knee_deg`` is the patient's measured value (a calibration), not the assumption: every
    stride of an unmeasured level says so (quality reason ``assumed_level``)."""
    plausible_knee_deg: tuple[float, float] = (-15.0, 160.0)
    """A knee angle outside this band [deg] cannot be true and is masked: hyperextension stops at ~5-10 deg
    (-15 deg is severe genu recurvatum); passive flexion ends at ~150-160 deg (heel against the buttock)."""
    implausible_warn_share: float = 0.01
    """A leg whose masked share of the knee angle (outside ``plausible_knee_deg``) reaches this, and that reports
    fewer strides than its gait strides, gets a session warning: the angle there was wrong, and the strides across it
    are not reported, so the axes or the level do not fit the leg (an independent simulator's running leg: 13 %
    masked, its 218 gait cycles all dropped, no word said). On the sweep (one seed per row) only the runs without
    quiet standing get it, whose level is GO's and 24 deg off (1 s masked, one stride lost): a fair warning."""
    implausible_warn_min_s: float = 1.0
    """... and that masked time [s] at least: a short trial's few masked samples are over the share without meaning
    much (the real 10 s trial with a 0.1 g accelerometer offset: 0.12 s, its lost strides dropped for another
    reason)."""


@dataclass(frozen=True)
class FusionParams:
    """The walking ``auto`` policy: absolute GO with CF fallback (:mod:`pipeline.policy`), and the level from the
    cycle-mean gravity that running uses too."""

    calm_dps: float = 90.0
    """Both segments slower than this [deg/s]: the accelerometer angle is usable (small lever-arm terms)."""
    midstance_window: tuple[float, float] = (0.10, 0.30)
    """Share of the stride (heel strike to heel strike) whose stance samples give the per-stride offset: mid-stance
    of Perry & Burnfield's gait phases (contralateral toe-off ~10 % to heel rise ~30 %): single support on a flat
    foot, so the heel-strike shock and its ringing (loading response, 0-10 %) and the push-off are outside, the
    shank is near vertical and both segments rotate slowly (small lever-arm terms of Seel Eq. 6)."""
    min_quiet_samples: int = 5
    """A stride with fewer calm stance samples uses its whole stance for the accelerometer level (and, unless its
    GO level comes from gravity, gets a note: ``few_quiet_samples``)."""
    gravity_level: bool = True
    """Level each walking stride over its mid-stance, each running cycle at its foot strike, from the cycle-mean gravity
    (:mod:`pipeline.cycle_gravity`; :func:`pipeline.policy.gravity_shifts` for running): no joint centre, impact, lever
    arm or soft-tissue term enters it. Walking strides without one (a hole, a clipped sample, a mean force off g: a
    jump, a step) take their gravity-levelled neighbours' (``gravity_min_cycles``), else keep the mid-stance
    accelerometer level. On an independent simulator (3-D knee and hip, thigh soft
    tissue, 50-200 Hz, true standing flexion given) the walking legs' peak bias SD 0.7-1.3 -> 0.4-0.6 deg, legs beyond 1
    deg 3-9 -> 0-3 of 16; on this repository's (tune seeds 0-3, calibrated) fast walking -0.42 +- 0.33 -> -0.07 +- 0.21,
    normal unchanged, 3-D hip and knee x2 with a 6 deg varus -0.41 +- 1.67 -> -0.57 +- 1.16 (read at the heel strike
    instead, where the thigh leans 20-30 deg: -0.84 +- 1.60)."""
    gravity_tol_mps2: float = 1.0
    """A stride or cycle gives its level from gravity only where the mean specific force over it lies within this
    [m/s^2] of g on both sensors: the velocity returned at the cycle's end (a jump or a step up does not; a start or a
    stop changes mostly the horizontal velocity, which tilts both segments' gravity by the same world angle and cancels
    in the knee) and the gyros carried the frame through it. On the simulator's runs the norms lie within 0.5 of g
    (5th-95th percentile, 100-200 Hz, 3-D hip and knee x2); 1 m/s^2 along the vertical is 6 % of g."""
    gravity_min_cycles: int = 3
    """Least strides or cycles with a gravity level of their own for a leg's gravity level to reach further. Running:
    fewer cycles leave the filter's level as it is. Walking: each stride without one (a hole or a saturated sample in
    it, which the gyros cannot carry gravity through; a mean force off g: a jump, a step) within ``offset_smooth``
    strides of them takes their level (running median over them, interpolated in time) instead of its accelerometer
    mid-stance level (:func:`pipeline.policy._gravity_filled`): a leg's stance level changes slowly from stride to
    stride, and the accelerometer's rests on the joint centres and lever arms, which failed leg by leg on an
    independent simulator with 3-D knees. Under 10 % bursty packet loss, where most strides hold a hole, held-out
    legs there carried their own level 4-6 deg off (peak LoA -8.6 .. 5.2 deg, 12 % of trend strides more than 5 deg
    off); from the neighbours' gravity -3.7 .. 1.6 and none (README, Accuracy)."""
    offset_smooth: int = 11
    """Running median width [strides] of the per-stride offsets: the true minimum changes slowly."""
    drift_max_deg: float = 15.0
    """GO drift [deg] between two updates beyond which the stride falls back to CF."""
    mismatch_deg: float = 8.0
    """SD [deg] of GO minus CF over a stride beyond which the stride gets a mismatch note."""
    bridge_disagree_deg: float = 3.0
    """The level carried from standing by the gyros (:mod:`pipeline.quiet_bridge`) checks the strides' mid-stance level
    (from each stride's gravity or its neighbours', else the accelerometer angle): where the two differ by more than
    this [deg] (median over the leg's strides that have both), the leg takes the bridged level. The accelerometer's
    mid-stance level rests on the joint centres and the thigh-shank clock and fails by 10-30 deg when they fail;
    gravity's rests on the axes and the clock only; the bridge on static angles only. Where nothing failed the bridge
    and the accelerometer level agreed within 2.45 deg on every leg of the sweep's tune seeds (p95 1.0), so agreeing
    legs keep the validated mid-stance level. 4 deg before the bridges stopped at turns (max 3.4 then); 3 deg was
    better than 4 on the independent simulator's tune seeds and on its held-out ones (README, Accuracy)."""
    bridge_min_strides: int = 3
    """Strides with both levels that the check needs."""
    bridge_anchor_s: float = 0.5
    """Quiet standing [s] at either end of a walk whose static accelerometer angle (median) anchors the
    integration."""
    bridge_max_span_s: float = 60.0
    """Longest run of motion [s] between two standing periods that is bridged (a gyro's residual bias changes little
    within a minute; a longer walk keeps the mid-stance level)."""
    bridge_max_turn_deg: float = 45.0
    """A run in which the body turns by more than this [deg] (the thigh's rotation about its mean up direction,
    :func:`pipeline.quiet_bridge.heading_deg`) is not bridged (as a run with a hole): the turn adds a step of up to
    its angle times the sine of the axes' misalignment (:func:`pipeline.quiet_bridge.bridged_angle`). Straight
    walking rocks the thigh by the hip's rotation only (+-5 deg), a U-turn by 150-180 deg."""
    bridge_max_drift_deg: float = 10.0
    """A bridge whose integral misses the static angle at its far end by more than this [deg] is not used: the
    axes, a hole or a posture change it cannot follow broke it."""


@dataclass(frozen=True)
class QualityParams:
    """Per-stride quality: 1 minus the penalties of its reasons, capped when the stride cannot be vouched for
    (:mod:`pipeline.quality`). Trends take strides of quality >= 0.5 (``server.trends.metrics.MIN_QUALITY``)."""

    penalties: tuple[tuple[str, float], ...] = (
        ("no_absolute_reference", 0.2), ("no_zero_crossing", 0.3), ("drift", 0.3), ("saturation", 0.5),
        ("go_cf_mismatch", 0.6), ("cf_fallback", 0.2), ("no_go_estimate", 0.3), ("few_quiet_samples", 0.1),
        ("bridged_gap", 0.1), ("event_in_gap", 0.2), ("bout_edge", 0.1), ("assumed_level", 0.0))
    """Quality lost per reason (quality = 1 - sum, floored at 0): saturation and a broken GO weigh most. GO and CF
    disagreeing in shape within a stride leaves it below the trend threshold: on the sweep's tune seeds only 61 % of
    those strides were within 3 deg of the truth (p95 5 deg), and far fewer with long lever arms or around jumps."""
    default_penalty: float = 0.1
    """Quality lost for a reason not listed."""
    untrusted: tuple[str, ...] = ("peak_in_gap", "long_gap", "clock_disagreement", "side_in_doubt",
                                   "level_wander", "mounting_changed", "sensors_handled", "leg_mismatch", "turning")
    """Reasons that leave the stride's metrics unobserved or unmeasurable: quality is capped below the trend
    threshold."""
    leg_mismatch_share: float = 0.5
    """A leg whose strides fail ``go_cf_mismatch`` at least this often (of ``leg_mismatch_min_strides`` or more)
    keeps every stride out of trends (``leg_mismatch``): the failure is the leg's, not the strides'. An independent
    simulator's uncorrected 39 ms thigh-shank clock offset left 27 of 30 strides mismatched and the other 3, 12 deg
    high like them, in trends."""
    leg_mismatch_min_strides: int = 6
    """Fewest strides a leg's mismatch share is judged on."""
    untrusted_cap: float = 0.3
    """Quality ceiling of a stride with an untrusted reason."""
    peak_lead_s: float = 0.15
    """A hole that ends up to this long [s] before a stride's swing peak counts as under the peak
    (``peak_in_gap``): the peak closes the swing-flexion rise (~0.15 s from toe-off, at 300-400 deg/s), and the
    integrated estimate carries any error of a modelled rise into the peak. Applies to fills longer than
    ``filled_peak_s`` (see there for the peak's change by hole length with the warped fill)."""
    filled_peak_s: float = 0.17
    """A hole filled from the neighbouring strides (:func:`pipeline.prepare.periodic_fill`) up to this long [s]
    leaves the swing peak and the minimum measured: one lost 20-sample packet at 128 Hz (0.164 s) or 16 samples at
    100 Hz. Holes cut into every third stride of loss-free tune sessions (100 Hz, seeds 0-2, 168 strides per cell),
    the warped fill: holes of 0.12-0.17 s centred 0-0.2 s before the peak moved it by p95 0.3-1.3 deg, max 3.6;
    0.2 s holes p95 0.7-1.8, max 5.2; 0.25 s p95 1.1-2.4, max 6.8 (uncut strides scatter ~0.5 deg SD around their
    leg's level). Longer fills there are ``peak_in_gap``."""
    trusted_fill_s: float = 0.5
    """A hole filled from the neighbouring strides longer than this [s] (half the shortest walking stride) makes
    every stride it touches ``long_gap``, out of trends: it may hold a whole swing or stance phase, whose shape and
    events are then the neighbours', not this stride's. Holes up to it were validated stride by stride
    (``filled_peak_s``); the longer fills up to ``PrepareParams.periodic_bridge_s`` keep the stride counted
    (coverage, the continuous trace) without vouching for its metrics."""
    bridged_peak_s: float = 0.1
    """A hole bridged by the cubic (``pipeline.prepare``, up to ``PrepareParams.max_bridge_s``) longer than this
    [s] at or within ``peak_lead_s`` before the swing peak makes the peak a model as well. Same experiment, holes
    centred 0-0.2 s before the peak: steps of ~0.10 s moved it by <= 1.5 deg (max), 0.11-0.12 s by <= 2.5 deg,
    0.13-0.14 s by <= 3.9 deg (p95 3.5); the uncut strides of the same runs moved by <= 0.4-1.5 deg. The knee's
    swing peak itself is a smooth maximum: a hole centred on it moves it no more than the uncut strides move."""
    max_turn_deg: float = 30.0
    """A stride over which the thigh and the shank both turn by more than this [deg] (heel strike to heel strike,
    :func:`pipeline.strapdown.cycle_turn_deg`: the body's change of heading) is a turning stride (``turning``, out of
    trends). Turning steps are another task than straight gait: the inner knee flexes less in swing, pivots and
    shuffle steps make stride-like curves that are no stride, and the knee moves most out of its hinge there; gait
    laboratories leave turns out of the strides they compare. On the simulator (tune seeds 0-1, 100 Hz) straight
    strides turn by 0.2-5 deg (p95), 18 at most next to a turn; strides of a 180 deg turn over 2.5 strides turn by
    18-123 deg, of three 90 deg turns per bout 30-92. A 400 m track's bend turns a running stride by ~5 deg, a
    corridor's corner by 45-90."""
    unmeasured_level: tuple[str, ...] = ("assumed_level",)
    """Reasons that leave the stride's absolute level an assumption (no calibration): its shape and ROM are
    measured, its peak and minimum flexion carry the unknown standing flexion (0-15 deg in patients), so it may
    enter trends (a constant offset does not move a slope) but is never scored as vouched for."""
    unmeasured_level_cap: float = 0.75
    """Quality ceiling of a stride whose level is assumed: below the 0.8 that means "accurate to a few degrees"."""

    def penalty(self, reason: str) -> float:
        """Quality lost for ``reason``."""
        return dict(self.penalties).get(reason, self.default_penalty)


@dataclass(frozen=True)
class RunningParams:
    """Running: foot strikes, gait-cycle windows, impact masks, 7 Hz low-pass, the running ``auto`` policy
    (:mod:`pipeline.running`, :mod:`pipeline.policy`, Rhudy et al. 2024 Sect. 2.2.2)."""

    fit_window: tuple[float, float] = (0.40, 0.80)
    """Share of the gait cycle used for the axis and centre fits (Rhudy Fig. 7: swing, no impacts)."""
    thigh_axis: Literal["principal", "hinge"] = "principal"
    """How the knee axes are found on those windows. ``"hinge"``: Seel's Eq. 2 with both axes free (Rhudy Eq. 2),
    levelled (``AxesParams.level_lean_deg``). ``"principal"``: the thigh's axis is its dominant rotation axis
    (McGrath et al. 2018; in a running swing the hip flexes through 60-80 deg while its ab/adduction and rotation
    span a few), the median over the gait cycles (:func:`pipeline.axes.median_principal_axis`, so a turn does not
    tilt it), and only the shank's is fitted by Eq. 2 against it (:func:`pipeline.axes.fit_shank_axis`). A knee is
    no hinge: the tibia turns about its long axis as the knee flexes, and with both axes free Eq. 2 tilts them
    together along a shallow valley of its cost (on the sweep's 150 s runs with 3-D hip and knee: 15-27 deg off the
    flexion axes, mostly in heading, and the trend strides' peaks 2-9 deg low). The price is paid by hinge knees
    whose hip moves in 3-D: the principal axis takes in the hip's ab/adduction and rotation (an independent
    simulator's hinge control: legs more than 3 deg off 0 -> 4 of 16, while its 3-D knees' worst legs went from -22
    to -7 deg). No measure found here tells the two apart reliably (the hinge fit's residual overlaps)."""
    impact_half_width: float = 0.05
    """Share of the gait cycle skipped on either side of a foot strike for measurement updates (Rhudy)."""
    lowpass_hz: float = 7.0
    """Zero-lag Butterworth cut-off [Hz] after the axes are known (Rhudy, after Vasquez et al.)."""
    lowpass_order: int = 4
    """Order of that Butterworth (Rhudy: 4th order)."""
    min_stride_s: float = 0.45
    """Shortest plausible running stride, same foot to same foot [s]."""
    max_stride_s: float = 1.6
    """Longest plausible running stride [s]."""
    impact_hp_hz: float = 12.0
    """Impacts are peaks of the shank acceleration's content above this frequency [Hz] (the ringing)."""
    strike_min_g: float = 0.5
    """An impact's high-frequency peak is at least this large [g]."""
    strike_rel: float = 0.4
    """... and at least this share of the session's impact level."""
    cycle_tol: float = 0.35
    """A cycle off the local median length by more than this share is not a gait cycle."""
    detect_max_stride_s: float = 0.85
    """``unknown`` sessions: runners strike every ~0.6-0.8 s, walkers every 0.9-1.4 s [s]."""
    detect_min_impact_g: float = 1.0
    """... with 4-10 g at the shank (high-frequency amplitude), walkers 1.5-3 g raw, far less high-pass [g]."""
    detect_min_cycles: int = 6
    """Fewer gait cycles are not evidence of running."""
    swing_peak_phase: tuple[float, float] = (0.55, 0.9)
    """Running knee flexion peaks within this share of the foot-strike cycle (Novacheck 1998): fixes the thigh axis
    sign."""
    shank_swing_window: tuple[float, float] = (0.6, 0.95)
    """Share of the foot-strike cycle in which the shank swings forward (the knee extends ahead of the next strike,
    Novacheck 1998): fixes the shank axis sign. Its largest rate is no sign: a rearfoot strike's stance dip can
    exceed the swing peak."""
    swing_peak_target: float = 0.7
    """Typical phase of that peak (~70 % of the cycle, Novacheck 1998): the sign whose peak is nearer wins."""
    default_stride_s: float = 0.7
    """Cycle length [s] for the impact mask when no plausible interval is known (a typical running stride)."""
    auto_estimator: str = "ekf"
    """The running ``auto`` estimator: best on the simulator without reference tuning (bench/accuracy.py)."""
    bridge_disagree_deg: float = 6.5
    """The check of the filter's level by the quiet standing around each run (:func:`pipeline.quiet_bridge.level_check`,
    whole standing-to-standing bridges only): beyond this [deg] the leg takes the bridged level. Wider than walking's
    (``FusionParams.bridge_disagree_deg``): with 3-D hip and knee motion the running knee rate about a hinge axis drifts
    more, and on the sweep's tune seeds (``joint_3d_mixed``, running 6 g) correct legs disagreed by up to 4.3 deg (1.5
    times that here); sensor positions put 20-30 cm off moved running legs by 4.5-10 deg (tune seeds 0-4). So only
    gross failures are caught."""
    level_wander_deg: float = 6.0
    """A running stride whose filter level against GO's (the mean of GO minus the filter's angle over the stride,
    :func:`pipeline.policy.go_offsets`) lies more than this [deg] from the leg's median is out of trends
    (``level_wander``). GO's zero, the knee's straightest moment before swing, is the same stride after stride in a
    steady run, so that level is constant unless the accelerometer updates drag the filter: on an independent
    simulator (sensors up to 25 cm from the knee, impacts to 10 g) 9 of 80 running legs drifted towards extension
    by 3-4 deg/s, 50-70 deg within a run, their strides scored 1.0; 130 of its 2685 running strides go out by it
    (83 of them more than 5 deg off). On this repository's simulator (tune seeds; 6 and 10 g, ringing impacts, 5 %
    bursty loss, lever arms x2, 3-D hip and knee) 3 of 1,764 running strides did, all with the 3-D knee."""
    bridge_min_fs_hz: float = 100.0
    """Lowest sample rate [Hz] at which the running level is checked: a running swing reaches 600-1000 deg/s with
    content up to ~20 Hz, and at 50 Hz the integral between rests drifted by several deg per run (accuracy bench,
    running at 50 Hz, tune seeds 0-9: |check| up to 8.3 deg with the filter's level right; none above 3 at 100 and
    200 Hz)."""
    no_reference_quality: float = 0.4
    """Stride quality without a quiet-standing zero: the level is then GO's (zero at the minimum before swing),
    which a running knee never reaches (it stays 10-25 deg flexed), so peak and minimum flexion may be off by that
    much; below 0.5 such strides stay out of trends (their ROM and timing are still right)."""


@dataclass(frozen=True)
class LongSessionParams:
    """Sessions longer than one chunk (a day of continuous monitoring) processed chunk by chunk
    (:mod:`pipeline.long_sessions`): memory bounded by the chunk, time linear in the length. Each chunk is a whole
    :func:`pipeline.session.process_session` run, so its joint-axis fit (Seel et al. 2014, Eq. 2) keeps the bounded
    sample budget of :class:`AxesParams` (``max_fit_samples`` over ``fit_chunks``) per chunk."""

    chunk_s: float = 1800.0
    """Longest session [s] processed in one block (shorter ones give exactly :func:`process_session`'s output), and
    the length of the owned part of each chunk of a longer one. Thirty minutes: hundreds of strides per chunk for
    the axis, centre and standing fits (one walking minute already gives the axis fit its 1000 samples), the
    processing of one chunk stays under 300 MB (bench/speed.py), and the overlap below adds only ~2 % to the work."""
    overlap_s: float = 20.0
    """Data [s] read on either side of a chunk's owned part: a stride (at most 3 s, ``PhaseParams.max_period_s``)
    starting just before the edge ends inside it, and the running medians over strides (11 and 15 strides,
    ``FusionParams.offset_smooth``, ``FilterInputParams.bias_smooth_strides``) see the same neighbours as in one
    block."""
    dedupe_s: float = 0.2
    """Strides of two chunks starting closer than this [s] are one stride (kept once, from the earlier chunk): the
    same heel strike found in both moves by milliseconds; two real strides of one leg are >= 0.45 s apart
    (``RunningParams.min_stride_s``)."""
    full_rate_trace_s: float = 3600.0
    """A chunked session up to this long [s] keeps its knee-angle trace at the sensors' rate (an hour at 100 Hz is
    0.36 million samples per leg); a longer one is stored at ``trace_max_fs_hz``."""
    trace_max_fs_hz: float = 25.0
    """Most samples per second [Hz] of the trace of a session longer than ``full_rate_trace_s`` (every k-th sample,
    k integer): a day at 100 Hz would be 4.3 million samples per leg; 25 Hz still shows every stride's flexion wave
    (gait content < 6 Hz; Allseits et al. 2018 filter at 6 Hz). Stride metrics are always computed at full rate."""


@dataclass(frozen=True)
class PipelineParams:
    """One value per stage of the pipeline."""

    prepare: PrepareParams = field(default_factory=PrepareParams)
    axes: AxesParams = field(default_factory=AxesParams)
    sync: SyncParams = field(default_factory=SyncParams)
    phases: PhaseParams = field(default_factory=PhaseParams)
    assignment: AssignmentParams = field(default_factory=AssignmentParams)
    metrics: MetricsParams = field(default_factory=MetricsParams)
    go: GoParams = field(default_factory=GoParams)
    cf: CfParams = field(default_factory=CfParams)
    kf: KfParams = field(default_factory=KfParams)
    tuning: TuningParams = field(default_factory=TuningParams)
    filter_inputs: FilterInputParams = field(default_factory=FilterInputParams)
    posture: PostureParams = field(default_factory=PostureParams)
    fusion: FusionParams = field(default_factory=FusionParams)
    quality: QualityParams = field(default_factory=QualityParams)
    running: RunningParams = field(default_factory=RunningParams)
    long_sessions: LongSessionParams = field(default_factory=LongSessionParams)
    mounting: MountingParams = field(default_factory=MountingParams)
    worn: WornParams = field(default_factory=WornParams)


WALKING = PipelineParams()
"""Walking preset (also the start for ``unknown`` sessions)."""
RUNNING = PipelineParams(phases=PhaseParams(search_s=0.2, stance_pct_range=(30.0, 85.0)))
"""Running preset. Strides of at most 85 % stance (walking's wider limit is for step-to gait). Its
toe-off is searched within 0.2 s before the swing lobe, not walking's 0.3 s: a running
stride is ~0.7 s and its swing lobe starts ~0.2 s after toe-off, so 0.3 s reached back into the loading response,
whose dip after a rearfoot strike is the deeper minimum, and the stance share (~18 %) failed
``PhaseParams.stance_pct_range`` (an independent running simulator: 34-63 % of strides found, 99-100 % with 0.2 s;
this repository's running rows unchanged). Running toe-off from a shank gyro is coarse whatever the rule
(the best of 18 published methods: limits of agreement +-150 ms against force plates in 74 runners, PMC10255839):
a running stride's stance time is indicative only."""
PRESETS: dict[str, PipelineParams] = {"walking": WALKING, "running": RUNNING}


def preset(activity: str) -> PipelineParams:
    """The named preset of ``activity`` (``walking`` for ``unknown``)."""
    return PRESETS.get(activity, WALKING)
