"""One session in, knee flexion per leg and per stride out: the pipeline's single public entry point.

prepare (units, common grid, gaps; :mod:`pipeline.prepare`) -> joint axes (Seel Eq. 2) and clock correction
(:mod:`pipeline.sync`) -> knee rate, shank sagittal rate, gait events (Allseits), joint centres and accelerometer
angle (Seel Eq. 5-7; :mod:`pipeline.walking` or :mod:`pipeline.running`) -> the ``auto`` policy or one estimator
(:mod:`pipeline.policy`) -> per-stride metrics (:mod:`pipeline.metrics`).
"""

from __future__ import annotations

import dataclasses
import math
import warnings as _warnings
from collections.abc import Mapping, Sequence

import numpy as np

from pipeline import ALGORITHM_VERSION
from pipeline.assignment import (
    centre_heights_m,
    check_segments,
    pairing_suspicious,
    segments_by_centre,
    side_verdict,
    swapped_pairing_better,
    weight_shift_dps,
)
from pipeline.bilateral import OtherLeg, gait_strides, mid_swings_s, non_alternating
from pipeline.constants import G_MPS2
from pipeline.estimators import get_estimator
from pipeline.leg_input import LegInput
from pipeline.level_walking import next_to, not_level_walking, stance_above_swing
from pipeline.metrics import stride_values_many
from pipeline.mounting import check_mounting, with_level_step
from pipeline.params import (
    RUNNING,
    AssignmentParams,
    PhaseParams,
    PipelineParams,
    PostureParams,
    QualityParams,
    preset,
)
from pipeline.phases import GaitEvents
from pipeline.policy import PolicyResult, auto, single_estimator
from pipeline.posture import thigh_upright_at
from pipeline.prepare import SI, to_si
from pipeline.quality import edge_reasons, gap_reasons, stride_quality, turn_reasons, with_reason
from pipeline.running import build_running_leg_input, detect_running
from pipeline.stepping import lowered_not_stepped
from pipeline.sync import SyncedLeg, stride_clock_runaway, synchronised_leg
from pipeline.types import (
    TRACE_WITHHELD_NO_GAIT,
    KneeCalibration,
    LegDiagnostics,
    LegResult,
    MountingCheck,
    RawSensorStream,
    RunningDiagnostics,
    SessionResult,
    StrideMetrics,
)
from pipeline.walking import build_walking_leg_input, gait_events
from pipeline.worn import blanked, joined, not_worn_spans_s, pieces_s


def process_session(streams: Sequence[RawSensorStream], activity: str = "walking", estimator: str = "auto",
                    params: PipelineParams | None = None,
                    calibration: Mapping[str, KneeCalibration] | None = None) -> SessionResult:
    """Knee flexion of every leg that has both a thigh and a shank stream.

    ``estimator``: ``"auto"`` (the activity's policy, :mod:`pipeline.policy`) or the name of one registered
    estimator (``"go"``, ``"cf"``, ...) run alone on the same prepared data. ``params``: the parameter tree
    (:mod:`pipeline.params`); None uses the activity's preset (``unknown``: walking, running for legs detected as
    running). ``calibration``: per leg, the measured standing knee flexion that replaces the preset's assumed
    ``posture.standing_knee_deg`` as the absolute zero (the leg's diagnostics say which was used).
    Raises ValueError only for unusable input (no streams, no samples, unknown estimator).
    """
    if estimator != "auto":
        get_estimator(estimator)  # fail early on an unknown name
    if not streams:
        raise ValueError("the session has no sensor streams")
    if all(np.asarray(s.t_s).size == 0 for s in streams):
        raise ValueError("the session has no samples")
    warnings: list[str] = []
    by_leg = _streams_by_leg(streams, warnings)
    session_params = params if params is not None else preset(activity)  # a leg's own preset may differ
    ap = session_params.assignment
    assigned: dict[str, str] = {}
    synced: dict[str, SyncedLeg] = {}
    # each leg's label check right before its synchronisation, sharing its streams' conversion (held for one leg
    # at a time); the label checks' warnings still come before the legs' own
    label_warnings: list[str] = []
    leg_warnings: list[str] = []
    for leg in sorted(by_leg):
        segs = by_leg[leg]
        if "thigh" not in segs or "shank" not in segs:
            missing = "thigh" if "thigh" not in segs else "shank"
            leg_warnings.append(f"{leg} leg skipped: no {missing} sensor")
            continue
        si = _check_labels(leg, segs, ap, assigned, label_warnings)
        try:
            synced[leg] = _synced(leg, segs["thigh"], segs["shank"], activity, params, si)
        except ValueError as exc:
            leg_warnings.append(f"{leg} leg skipped: {exc}")
        del si
    warnings += label_warnings + leg_warnings
    legs, swings, others = _processed_legs(synced, by_leg, activity, estimator, params, calibration, assigned,
                                           warnings)
    # after any veto of a label exchange: the sensors as they were finally taken
    warnings += _offset_warnings(synced, by_leg, session_params.posture)
    legs, swings = _check_thigh_pairing(legs, swings, by_leg, activity, estimator, params, calibration, ap, assigned,
                                        warnings, others)
    # the other leg's strides are judged against this leg as it was recorded, still where its sensors were off
    recorded_gaps = {leg: lr.gaps_s for leg, lr in legs.items()}
    legs, swings = _without_not_worn(legs, swings, by_leg, activity, estimator, params, calibration, assigned,
                                     others, warnings)
    # a leg's own gait strides (the other leg's swings do not contradict them) anchor it even where every one of them
    # failed a per-stride check (masked angles, holes); stair gait anchors it too
    unreported = {leg for leg, lr in legs.items() if not lr.strides and _has_gait(lr)}
    legs = _alternating_strides(legs, swings, warnings, recorded_gaps)
    gait_legs = unreported | {leg for leg, lr in legs.items() if lr.strides}
    legs = _level_strides(legs, session_params.phases, warnings)
    for leg in [leg for leg, how in assigned.items() if how == "thigh_shank_exchanged" and leg in legs
                and not legs[leg].strides]:
        if _keep_labels(leg, streams, activity, estimator, params, (calibration or {}).get(leg), others.get(leg),
                        legs, swings, by_leg, assigned, warnings):
            gait_legs.discard(leg)
    legs = _withhold_unanchored(legs, gait_legs, session_params.axes.min_gait_strides, warnings)
    legs = _check_sides(legs, ap, session_params.quality, warnings)
    warnings += _angle_warnings(legs, session_params.posture)
    _note_assignment(legs, assigned)
    return SessionResult(algorithm_version=ALGORITHM_VERSION, activity=activity, legs=legs, warnings=warnings)


def _note_assignment(legs: dict[str, LegResult], assigned: dict[str, str]) -> None:
    """Each leg's diagnostics say what the sensor-label checks did (in place)."""
    for leg, how in assigned.items():
        lr = legs.get(leg)
        if lr is not None and lr.diagnostics is not None:
            lr.diagnostics = dataclasses.replace(lr.diagnostics, assignment=how)


def _angle_warnings(legs: dict[str, LegResult], posture: PostureParams) -> list[str]:
    """The warnings about each shown knee angle: clocks that run apart, a sensor remounted, a level carried from
    standing, strides that were no steps (:mod:`pipeline.stepping`), strides lost to implausible angles
    (:func:`_implausible_warnings`)."""
    out = [f"{leg} leg: its thigh and shank clocks run apart faster than crystal clocks can; the knee angle's "
           "timing is unknown and its strides are kept out of trends (clock_disagreement)"
           for leg in sorted(legs) if _clock_unknown(legs[leg]) and not _withheld(legs[leg])]
    out += [_mounting_warning(leg, m) for leg in sorted(legs)
            if (m := _mounting(legs[leg])) is not None and m.changed and not _withheld(legs[leg])]
    out += [_level_bridged_warning(leg, d) for leg in sorted(legs)
            if (d := legs[leg].diagnostics) is not None and d.level_bridged and not _withheld(legs[leg])]
    out += [f"{leg} leg: {d.lowered_strides} stride(s) dropped: the thigh did not turn forward through the swing "
            "nor land forward of its push-off, no step forward (marching in place, side steps, a landing)"
            for leg in sorted(legs)
            if (d := legs[leg].diagnostics) is not None and d.lowered_strides and not _withheld(legs[leg])]
    return out + _implausible_warnings(legs, posture)


def _implausible_warnings(legs: dict[str, LegResult], posture: PostureParams) -> list[str]:
    """One warning per shown leg whose knee angle left ``PostureParams.plausible_knee_deg`` on at least
    ``implausible_warn_share`` of its samples and ``implausible_warn_min_s``, and that reports fewer strides than its
    gait strides: masked, so never shown, but the strides across it are gone too."""
    lo, hi = posture.plausible_knee_deg
    out = []
    for leg in sorted(legs):
        lr, d = legs[leg], legs[leg].diagnostics
        if d is None or _withheld(lr) or d.n_strides >= d.gait_strides:
            continue
        masked_s = d.masked_implausible_samples / lr.fs_hz
        if masked_s < posture.implausible_warn_min_s or \
                d.masked_implausible_samples < posture.implausible_warn_share * lr.angle_deg.size:
            continue
        out.append(f"{leg} leg: {masked_s:.0f} s of its knee angle lay outside "
                   f"{lo:g} .. {hi:g} deg, which no knee reaches, and are not shown; {d.n_strides} of its "
                   f"{d.gait_strides} gait strides are reported. The knee axes or the level do not fit this leg: "
                   "check the sensors' placement and labels")
    return out


def _mounting_warning(leg: str, m: MountingCheck) -> str:
    """The session warning of a leg whose mounting changed (:mod:`pipeline.mounting`): what moved, and when."""
    moved = [f"the knee axis moved {m.thigh_deg:.0f} deg in the thigh sensor's frame, {m.shank_deg:.0f} deg in the "
             "shank's"] if m.thigh_deg is not None and m.shank_deg is not None else []
    if m.level_step_deg is not None:
        moved.append(f"the level stepped by {m.level_step_deg:.0f} deg in standing and walking alike")
    at = "" if m.at_s is None else f" near {m.at_s:.0f} s"
    return (f"{leg} leg: a sensor's mounting changed{at} ({'; '.join(moved)}): one set of axes and one level do not "
            "fit the whole session, so its strides are kept out of trends (mounting_changed); keep the straps in "
            "place, or start a new session after re-fastening one")


def _level_bridged_warning(leg: str, d: LegDiagnostics) -> str:
    """The session warning of a leg that took the level carried from standing (``level_bridged``), with the check of
    its CF fallback strides when they had their own."""
    own = d.fallback_bridge_check_deg
    fallback = "" if own is None or own == d.bridge_check_deg else f" ({own:+.1f} deg on its CF fallback strides)"
    return (f"{leg} leg: the knee angle's level in motion disagreed with the level carried from the standing around "
            f"the walks by {d.bridge_check_deg:+.1f} deg{fallback}; the latter was used (level_bridged)")


def _offset_warnings(synced: Mapping[str, SyncedLeg], by_leg: Mapping[str, Mapping[str, RawSensorStream]],
                     posture: PostureParams) -> list[str]:
    """One warning per sensor whose accelerometer read at least ``rest_offset_warn_mps2`` off at rest: it was
    removed as far as the rests show it, but such a sensor's unseen part still moves the level by degrees (the
    sweep's ``sensor`` axis), and the sensor wants calibrating. The text holds the threshold, not the fitted value
    (that is in the leg's diagnostics), so a long session's chunks say it once."""
    out = []
    limit = posture.rest_offset_warn_mps2
    for leg in sorted(synced):
        prep = synced[leg].prep
        for seg, off in (("thigh", prep.acc_offset_thigh_mps2), ("shank", prep.acc_offset_shank_mps2)):
            if float(np.linalg.norm(off)) >= limit:
                out.append(f"{leg} {seg} sensor {by_leg[leg][seg].sensor_id}: its accelerometer reads at least "
                           f"{limit:g} m/s^2 ({limit / G_MPS2:.2f} g) off at rest; removed as far as the session's "
                           "rests show it, the knee level may still be off by degrees: calibrate the sensor")
    return out


def _check_labels(leg: str, segs: dict[str, RawSensorStream], params: AssignmentParams, assigned: dict[str, str],
                  warnings: list[str]) -> tuple[SI, SI]:
    """Exchange the leg's thigh and shank streams in ``segs`` when their motion says the labels are swapped
    (:func:`pipeline.assignment.check_segments`; what was done goes to ``assigned``). Returns the two streams'
    :func:`pipeline.prepare.to_si` (thigh, shank, after any exchange), for the leg's preparation to reuse."""
    si = {seg: to_si(segs[seg]) for seg in ("thigh", "shank")}
    chk = check_segments(segs["thigh"], segs["shank"], params, (si["thigh"], si["shank"]))
    ratios = f"shank/thigh swing rate {chk.rate_ratio:.2f}, impact {chk.impact_ratio:.2f}"
    if chk.verdict == "swapped":
        segs["thigh"], segs["shank"] = segs["shank"], segs["thigh"]
        si["thigh"], si["shank"] = si["shank"], si["thigh"]
        assigned[leg] = "thigh_shank_exchanged"
        warnings.append(f"{leg} leg: the sensor labelled thigh moves like a shank ({ratios}); "
                        "thigh and shank labels exchanged")
    return si["thigh"], si["shank"]


def _withdraw_exchange(leg: str, warnings: list[str]) -> None:
    """Take back the warning of :func:`_check_labels` that exchanged the leg's thigh and shank (in place)."""
    warnings[:] = [w for w in warnings if not w.startswith(f"{leg} leg: the sensor labelled thigh moves like a shank")]


def _processed_legs(synced: dict[str, SyncedLeg], by_leg: dict[str, dict[str, RawSensorStream]], activity: str,
                    estimator: str, params: PipelineParams | None,
                    calibration: Mapping[str, KneeCalibration] | None, assigned: dict[str, str],
                    warnings: list[str]) -> tuple[dict[str, LegResult], dict[str, np.ndarray], dict[str, OtherLeg]]:
    """Every synchronised leg processed (:func:`_each_leg`); all again where the joint centres veto an exchange of
    thigh and shank (:func:`_centre_vetoes`; ``synced`` re-synchronised in place, a leg that cannot be is skipped
    with a warning), since the other leg's swings change with it. Returns the legs, their mid-swing times and the
    other legs' swings."""
    ap = (params if params is not None else preset(activity)).assignment
    legs, swings, others, skipped = _each_leg(synced, by_leg, activity, estimator, params, calibration)
    # a vetoed leg changes the other's swings, and an exchanged leg that showed no stride may show some now: judged
    # again until none is vetoed (a veto takes a leg's exchange back, so this ends after one pass per leg)
    while vetoed := _centre_vetoes(legs, by_leg, assigned, warnings, ap):
        for leg in vetoed:
            try:
                synced[leg] = _synced(leg, by_leg[leg]["thigh"], by_leg[leg]["shank"], activity, params)
            except ValueError as exc:
                del synced[leg]
                warnings.append(f"{leg} leg skipped: {exc}")
        legs, swings, others, skipped = _each_leg(synced, by_leg, activity, estimator, params, calibration)
    warnings += skipped
    return legs, swings, others


def _each_leg(synced: dict[str, SyncedLeg], by_leg: dict[str, dict[str, RawSensorStream]], activity: str,
              estimator: str, params: PipelineParams | None, calibration: Mapping[str, KneeCalibration] | None
              ) -> tuple[dict[str, LegResult], dict[str, np.ndarray], dict[str, OtherLeg], list[str]]:
    """Every synchronised leg processed (:func:`_process_leg`) with the other leg's swings (:func:`_other_legs`):
    the legs, their mid-swing times, the other legs' swings and the warnings of the legs skipped."""
    events = _leg_events(synced, activity, params)
    others = _other_legs(synced, events, params if params is not None else preset(activity))
    legs: dict[str, LegResult] = {}
    swings: dict[str, np.ndarray] = {}
    skipped: list[str] = []
    for leg in sorted(synced):
        segs = by_leg[leg]
        try:
            legs[leg], swings[leg] = _process_leg(leg, segs["thigh"], segs["shank"], activity, estimator, params,
                                                  (calibration or {}).get(leg), synced[leg], others.get(leg),
                                                  events.get(leg))
        except ValueError as exc:
            skipped.append(f"{leg} leg skipped: {exc}")
    return legs, swings, others, skipped


def _centre_vetoes(legs: dict[str, LegResult], by_leg: dict[str, dict[str, RawSensorStream]],
                   assigned: dict[str, str], warnings: list[str], ap: AssignmentParams) -> list[str]:
    """The legs whose thigh and shank the swing rates exchanged but the joint centres do not confirm it by putting the
    sensor taken for the thigh higher above the knee than the one taken for the shank
    (:func:`pipeline.assignment.segments_by_centre`; they may put it lower, or fit no body-worn lever arms).
    Their streams are put back as labelled in ``by_leg`` (``assigned`` and ``warnings`` in place), to be processed
    again: high knees or marching lift the thigh faster than gait swings the shank, and the exchanged order took
    their lifts for strides (and, between walks, lost the walk's). Only legs whose exchanged order shows strides are
    judged: one without any is left to :func:`_keep_labels`, which takes the labels back too and keeps no stride (a
    step test alone)."""
    vetoed = []
    for leg in [leg for leg, how in assigned.items()
                if how == "thigh_shank_exchanged" and leg in legs and legs[leg].strides]:
        d = legs[leg].diagnostics
        heights = None if d is None else d.centre_heights_m
        verdict = segments_by_centre(heights, ap)
        if verdict == "as_labelled":
            continue
        segs = by_leg[leg]
        segs["thigh"], segs["shank"] = segs["shank"], segs["thigh"]
        del assigned[leg]
        _withdraw_exchange(leg, warnings)
        where = (f"the joint centres put the sensor labelled thigh {heights[1] - heights[0]:.2f} m higher above the "
                 "knee than the one labelled shank") if verdict == "swapped" and heights is not None \
            else "the joint centres do not confirm it"
        warnings.append(f"{leg} leg: thigh and shank labels kept as given: the swing rates read them as exchanged "
                        f"(exercises that lift the thigh fast), but {where}")
        vetoed.append(leg)
    return vetoed


def _keep_labels(leg: str, streams: Sequence[RawSensorStream], activity: str, estimator: str,
                 params: PipelineParams | None, calibration: KneeCalibration | None, other: OtherLeg | None,
                 legs: dict[str, LegResult], swings: dict[str, np.ndarray],
                 by_leg: dict[str, dict[str, RawSensorStream]], assigned: dict[str, str], warnings: list[str]) -> bool:
    """Process ``leg`` again with its thigh and shank as labelled (in place) after an exchange that left it without
    a gait stride (after the alternation and level-walking drops). The swing-rate rule
    (:func:`pipeline.assignment.check_segments`) reads gait: a step test, jumps, squats, sit-to-stand or marching in
    place move the thigh faster than the shank (rate ratio 0.03-0.56 on the simulators), and every exercise-only
    session of an independent simulator had its labels exchanged. Without gait nothing confirms the exchange, so the
    labels stand; but a shank that swings slower than its thigh is not walking either (in gait it swings 2-3 x
    faster), so whatever strides the labelled order shows are dropped (a step test alone gave 227 strides of trend
    quality there, peaks ~20 deg against a true 70). An exchange whose order shows strides is judged by the joint
    centres first (:func:`_centre_vetoes`). False when the leg could not be processed as labelled (left as it
    was)."""
    segs = _streams_by_leg(streams, [])[leg]
    try:
        synced = _synced(leg, segs["thigh"], segs["shank"], activity, params)
        legs[leg], swings[leg] = _process_leg(leg, segs["thigh"], segs["shank"], activity, estimator, params,
                                              calibration, synced, other)
    except ValueError:
        return False
    by_leg[leg] = segs
    del assigned[leg]
    _withdraw_exchange(leg, warnings)
    dropped = len(legs[leg].strides)
    legs[leg] = legs[leg].without(set(range(dropped)))
    warnings.append(f"{leg} leg: thigh and shank labels kept as given: the swing rates read them as exchanged, but "
                    f"the leg has no gait stride either way (the shank swings slower than the thigh: not walking; "
                    f"{dropped} stride(s) dropped)")
    return True


def _centre_residuals(legs: dict[str, LegResult]) -> tuple[float, float] | None:
    """Joint-centre fit residuals [m/s^2] of the left and right leg (None without diagnostics)."""
    d = [legs[k].diagnostics for k in ("left", "right")]
    if d[0] is None or d[1] is None:
        return None
    return d[0].centre_rms_residual_mps2, d[1].centre_rms_residual_mps2


def _check_thigh_pairing(legs: dict[str, LegResult], swings: dict[str, np.ndarray],
                         by_leg: dict[str, dict[str, RawSensorStream]], activity: str,
                         estimator: str, params: PipelineParams | None,
                         calibration: Mapping[str, KneeCalibration] | None, ap: AssignmentParams,
                         assigned: dict[str, str], warnings: list[str], others: Mapping[str, OtherLeg]
                         ) -> tuple[dict[str, LegResult], dict[str, np.ndarray]]:
    """Both legs processed again with the thighs exchanged when a joint-centre residual is suspicious; the swapped
    pairing is kept when it fits clearly better (:func:`pipeline.assignment.swapped_pairing_better`) and shows a
    stride: without gait the residuals confirm nothing (marching in place alone, whose thigh and shank labels the
    swing rates had already exchanged, fitted the other leg's sensors better on 3 of 5 report seeds, and its knee
    angles then read 11 deg off)."""
    if set(legs) != {"left", "right"}:
        return legs, swings
    labelled = _centre_residuals(legs)
    if labelled is None or not pairing_suspicious(labelled, ap):
        return legs, swings
    other = {"left": "right", "right": "left"}
    try:
        runs = {k: _process_leg(k, by_leg[other[k]]["thigh"], by_leg[k]["shank"], activity, estimator, params,
                                (calibration or {}).get(k), other=others.get(k)) for k in ("left", "right")}
    except ValueError:
        runs = {}
    swapped = {k: v[0] for k, v in runs.items()}
    resid = _centre_residuals(swapped) if swapped else None
    if resid is not None and swapped_pairing_better(labelled, resid, ap) and any(lr.strides for lr in swapped.values()):
        for k in ("left", "right"):
            assigned[k] = "thighs_exchanged_between_legs"
        warnings.append("thigh sensors exchanged between the legs: each fits the other leg's shank as a hinge "
                        f"(joint-centre residual {labelled[0]:.2f}/{labelled[1]:.2f} -> {resid[0]:.2f}/{resid[1]:.2f}"
                        " m/s^2, left/right)")
        return swapped, {k: v[1] for k, v in runs.items()}
    return legs, swings


def _alternating_strides(legs: dict[str, LegResult], swings: dict[str, np.ndarray], warnings: list[str],
                         gaps_s: Mapping[str, Sequence[tuple[float, float]]]) -> dict[str, LegResult]:
    """Each leg without the strides in which the other leg does not swing in anti-phase (jumps, squats,
    sit-to-stand: :mod:`pipeline.bilateral`); a leg alone is not judged, nor is a leg whose shank clock is unknown
    or judged against one (its swings may lie anywhere). ``gaps_s``: per leg, where it has no data to judge by."""
    if set(legs) != {"left", "right"}:
        return legs
    out = dict(legs)
    for leg, other in (("left", "right"), ("right", "left")):
        lr = legs[leg]
        if not lr.strides or _clock_unknown(lr) or _clock_unknown(legs[other]):
            continue
        t0, to, t1 = np.array([(s.t_start_s, s.t_toe_off_s, s.t_end_s) for s in lr.strides]).T
        spans = np.column_stack([t0, mid_swings_s(np.sort(swings[leg]), to, t1), t1])
        drop = set(non_alternating(spans, swings[other], gaps_s[other]))
        if drop:
            out[leg] = lr.without(drop)
            warnings.append(f"{leg} leg: {len(drop)} stride(s) dropped: the other leg did not swing in anti-phase "
                            "(not gait)")
    return out


def _without_not_worn(legs: dict[str, LegResult], swings: dict[str, np.ndarray],
                      by_leg: Mapping[str, Mapping[str, RawSensorStream]], activity: str, estimator: str,
                      params: PipelineParams | None, calibration: Mapping[str, KneeCalibration] | None,
                      assigned: Mapping[str, str], others: Mapping[str, OtherLeg], warnings: list[str]
                      ) -> tuple[dict[str, LegResult], dict[str, np.ndarray]]:
    """Each leg whose sensors were off the leg for a while (``LegDiagnostics.not_worn_s``, :mod:`pipeline.worn`)
    shows nothing there (:func:`pipeline.worn.blanked`); where the sensors were handled (``handled_s``) the pieces
    on either side are processed again apart, each learning its own knee axes and level, since the sensors may have
    been put back on otherwise and the handling itself is no knee motion for the hinge fit
    (:func:`pipeline.worn.pieces_s`, :func:`pipeline.worn.joined`)."""
    out, out_swings = dict(legs), dict(swings)
    tree = params if params is not None else preset(activity)
    for leg, lr in legs.items():
        if lr.diagnostics is None or not lr.diagnostics.not_worn_s:
            continue
        spans, handled = lr.diagnostics.not_worn_s, lr.diagnostics.handled_s
        if handled:
            thigh_leg = {"left": "right", "right": "left"}[leg] \
                if assigned.get(leg) == "thighs_exchanged_between_legs" else leg
            thigh, shank = by_leg[thigh_leg]["thigh"], by_leg[leg]["shank"]
            parts: list[tuple[LegResult, np.ndarray]] = []
            for t0, t1 in pieces_s(handled, float(lr.t_s[0]), float(lr.t_s[-1]), tree.worn):
                try:
                    parts.append(_process_leg(leg, _within(thigh, t0, t1), _within(shank, t0, t1), activity,
                                              estimator, params, (calibration or {}).get(leg),
                                              other=others.get(leg)))
                except ValueError:  # too little there to process: that piece shows nothing
                    continue
            lr, out_swings[leg] = joined(lr, _trusted_pieces(parts, lr, tree))
        out[leg] = blanked(lr, spans, handled)
        where = ", ".join(f"{t0:.0f}-{t1:.0f} s" for t0, t1 in spans)
        apart = " (the sensors were handled: the leg's axes and level learned apart on either side)" if handled else ""
        warnings.append(f"{leg} leg: sensors not on the leg at {where} (turned unlike a knee, or at rest, not "
                        f"standing, while the other leg walked): no knee angle there{apart} (not_worn_s)")
    return out, out_swings


def _trusted_pieces(parts: list[tuple[LegResult, np.ndarray]], whole: LegResult, params: PipelineParams
                    ) -> list[tuple[LegResult, np.ndarray]]:
    """``parts`` whose strides trends may take: a piece shorter than ``WornParams.trusted_piece_s`` keeps them out
    (``sensors_handled``: too short for its own mounting check), and the piece holding the mounting change the leg
    processed ``whole`` showed (:mod:`pipeline.mounting`) too (``mounting_changed``, said in its diagnostics); a
    change that fell between two pieces was where the sensors were handled, and the pieces learned their axes
    apart."""
    m = _mounting(whole)
    out = []
    for part, swings in parts:
        if part.t_s.size and part.t_s[-1] - part.t_s[0] < params.worn.trusted_piece_s:
            part = dataclasses.replace(part, strides=with_reason(part.strides, "sensors_handled", params.quality))
        if m is not None and m.changed and m.at_s is not None and part.t_s.size \
                and part.t_s[0] <= m.at_s <= part.t_s[-1]:
            diag = None if part.diagnostics is None else dataclasses.replace(part.diagnostics, mounting=m)
            part = dataclasses.replace(part, strides=with_reason(part.strides, "mounting_changed", params.quality),
                                       diagnostics=diag)
        out.append((part, swings))
    return out


def _rounded_spans(spans: Sequence[tuple[float, float]]) -> tuple[tuple[float, float], ...]:
    """``spans`` [s] to the hundredth, outwards: the blanking reads them back, and a span rounded inwards left the
    sample at its end shown."""
    return tuple((math.floor(a * 100.0) / 100.0, math.ceil(b * 100.0) / 100.0) for a, b in spans)


def _within(stream: RawSensorStream, t0: float, t1: float) -> RawSensorStream:
    """``stream``'s samples from ``t0`` to ``t1`` [s] (its times increase: two binary searches, one slice)."""
    t = np.asarray(stream.t_s)
    keep = slice(int(np.searchsorted(t, t0, side="left")), int(np.searchsorted(t, t1, side="right")))
    return dataclasses.replace(stream, t_s=t[keep], gyr=np.asarray(stream.gyr)[keep],
                               acc=np.asarray(stream.acc)[keep])


def _level_strides(legs: dict[str, LegResult], params: PhaseParams, warnings: list[str]) -> dict[str, LegResult]:
    """Each walking leg without the strides whose knee stays near extension for too little of the stride (stairs,
    step-ups: :mod:`pipeline.level_walking`); a running leg is not judged, nor is one whose shank clock is unknown
    (its angle's shape is)."""
    out = dict(legs)
    for leg, lr in legs.items():
        if lr.activity != "walking" or not lr.strides or _clock_unknown(lr):
            continue
        spans = np.array([(s.t_start_s, s.t_end_s) for s in lr.strides])
        stairs = not_level_walking(lr.angle_deg, lr.t_s, spans, params.level_band_deg, params.level_min_share)
        downs = [k for k in stance_above_swing(lr.strides, params.stance_above_swing_deg) if k not in stairs]
        onto = next_to(spans, [*stairs, *downs])
        if stairs:
            warnings.append(f"{leg} leg: {len(stairs)} stride(s) dropped: the knee stayed near extension for less "
                            f"than {params.level_min_share:.0%} of the stride (stairs or step-ups, not level gait)")
        if downs:
            warnings.append(f"{leg} leg: {len(downs)} stride(s) dropped: the knee flexed more in stance than in swing "
                            "(stepping down, not level gait)")
        if onto:
            warnings.append(f"{leg} leg: {len(onto)} stride(s) dropped: the stride led onto or off a stair or a step")
        if stairs or downs:
            out[leg] = lr.without({*stairs, *downs, *onto})
    return out


def _has_gait(lr: LegResult) -> bool:
    """Whether the leg's gait events delimit strides that the other leg's swings do not contradict."""
    return lr.diagnostics is not None and lr.diagnostics.gait_strides > 0


def _mounting(lr: LegResult) -> MountingCheck | None:
    """The leg's mounting-change check (:mod:`pipeline.mounting`), None where it did not run."""
    return None if lr.diagnostics is None else lr.diagnostics.mounting


def _withheld(lr: LegResult) -> bool:
    """Whether the leg's trace was withheld (:func:`_withhold_unanchored`)."""
    return lr.diagnostics is not None and lr.diagnostics.trace_withheld is not None


def _withhold_unanchored(legs: dict[str, LegResult], gait_legs: set[str], min_gait_strides: int,
                         warnings: list[str]) -> dict[str, LegResult]:
    """Each leg without a gait stride loses its knee-angle trace (every sample NaN, ``trace_withheld``): none of the
    strides its gait events delimit survives the other leg's anti-phase check, or a label exchange was undone
    (:func:`_keep_labels`); ``gait_legs`` are the others. A still other leg (its sensors not worn) contradicts
    every stride too: such a leg loses its strides already (:func:`_alternating_strides`), and its trace with them.
    A leg with fewer than ``min_gait_strides`` (``AxesParams.min_gait_strides``) loses its trace and its strides.

    The knee axes (Seel et al. 2014 Eq. 2 orients them by the swing), the upright directions that tell standing from
    sitting, and so the absolute zero (:mod:`pipeline.posture`) are all learned from gait. Without it they are
    unanchored: seated knee extensions keep the thigh still (its axis is unobservable), and on exercise-only
    sessions of two simulators (sitting, seated extensions, sit-to-stand, jumps, a step test; no walking) the trace
    was 10-100 deg off, with the seated knee read near 0 deg. A gait stride dropped later as stair gait still counts:
    it turns the knee about the same axis (stair-only sessions: trace RMSE 0.7-1.7 deg). One or two strides of a
    turn on the spot do not anchor it: where a leg's own steps give no strides (crutch gait on an independent
    simulator), they set the signs and zero of a trace 15-45 deg off."""
    out = dict(legs)
    for leg in sorted(legs):
        lr = legs[leg]
        diag = lr.diagnostics
        n_gait = 0 if diag is None else diag.gait_strides
        if leg in gait_legs and n_gait >= min_gait_strides:
            continue
        few = leg in gait_legs
        if few:
            lr = lr.without(set(range(len(lr.strides))))
            diag = lr.diagnostics
        if diag is not None:
            diag = dataclasses.replace(diag, trace_withheld=TRACE_WITHHELD_NO_GAIT)
        out[leg] = dataclasses.replace(lr, angle_deg=np.full_like(lr.angle_deg, np.nan),
                                       estimator=np.full(lr.estimator.shape, "", dtype=lr.estimator.dtype),
                                       diagnostics=diag)
        if few:
            warnings.append(f"{leg} leg: no knee angle: only {n_gait} gait stride(s) in the session, too few to learn "
                            f"the knee axes and the angle's zero from (at least {min_gait_strides}: a turn on the "
                            "spot or a single step, not a walk); its strides and trace are withheld (trace_withheld)")
        else:
            warnings.append(f"{leg} leg: no knee angle: no gait stride in the session to learn the knee axes and the "
                            "angle's zero from (exercises or sitting alone, or strides the other leg's swings "
                            "contradict: jumps, squats, or that leg's sensors not worn); the trace is withheld "
                            "(trace_withheld)")
    return out


def _check_sides(legs: dict[str, LegResult], ap: AssignmentParams, qp: QualityParams, warnings: list[str]
                 ) -> dict[str, LegResult]:
    """Both legs with every stride ``side_in_doubt`` (out of trends) when their thighs' weight shifts say the left
    and right labels are swapped (:func:`pipeline.assignment.side_verdict`); unchanged otherwise. Never corrected on
    this cue alone: a wrong exchange would put each knee's strides into the other's trend. Judged only where both
    legs keep ``shift_min_strides`` gait strides after the drops (a session of stair flights has none: its weight
    shifts are not gait's)."""
    if set(legs) != {"left", "right"} or min(len(lr.strides) for lr in legs.values()) < ap.shift_min_strides:
        return legs
    shift = {leg: None if lr.diagnostics is None else lr.diagnostics.weight_shift_dps for leg, lr in legs.items()}
    if side_verdict(shift["left"], shift["right"], ap) != "swapped":
        return legs
    warnings.append(f"left and right labels look swapped: each thigh shifts its weight in early stance the way "
                    f"the other leg's would (left {shift['left'][0]:+.1f}, right {shift['right'][0]:+.1f} deg/s), so "
                    "the thigh sensors, and perhaps the shank sensors too, sit on the other legs; every stride is kept "
                    "out of trends (side_in_doubt): confirm the sides in the app")
    return {leg: dataclasses.replace(lr, strides=with_reason(lr.strides, "side_in_doubt", qp))
            for leg, lr in legs.items()}


def _clock_unknown(lr: LegResult) -> bool:
    """Whether the leg's shank clock could not be brought onto its thigh's (``LegDiagnostics.clock_disagreement``)."""
    return lr.diagnostics is not None and lr.diagnostics.clock_disagreement


def _streams_by_leg(streams: Sequence[RawSensorStream], warnings: list[str]
                    ) -> dict[str, dict[str, RawSensorStream]]:
    """Thigh and shank stream per leg; of several sensors on one segment the one with most samples (warned)."""
    by_leg: dict[str, dict[str, RawSensorStream]] = {}
    for s in streams:
        slot = by_leg.setdefault(s.leg, {})
        if s.segment in slot:
            keep = max(slot[s.segment], s, key=lambda x: np.asarray(x.t_s).size)
            warnings.append(f"{s.leg} {s.segment}: several sensors ({slot[s.segment].sensor_id}, {s.sensor_id}); "
                            f"using {keep.sensor_id}")
            slot[s.segment] = keep
        else:
            slot[s.segment] = s
    return by_leg


def _synced(leg: str, thigh: RawSensorStream, shank: RawSensorStream, activity: str, params: PipelineParams | None,
            si: tuple[SI, SI] | None = None) -> SyncedLeg:
    """:func:`pipeline.sync.synchronised_leg` with the session's parameters (runtime warnings of NaN-heavy
    input silenced, as for the whole leg). ``si``: both streams already converted (:func:`_check_labels`)."""
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore", RuntimeWarning)
        return synchronised_leg(leg, thigh, shank, params if params is not None else preset(activity), si=si)


def _leg_events(synced: Mapping[str, SyncedLeg], activity: str, params: PipelineParams | None
               ) -> dict[str, tuple[np.ndarray, GaitEvents]]:
    """Per leg of a two-legged session, :func:`pipeline.walking.gait_events` of its synchronised data: the shank's
    gait events, which do not depend on the thigh axis, so the other leg's check (:func:`_other_legs`) and the
    leg's own walking input use the same ones."""
    if set(synced) != {"left", "right"}:
        return {}
    p = params if params is not None else preset(activity)
    return {leg: gait_events(sl.prep, sl.axes, p) for leg, sl in synced.items()}


def _other_legs(synced: Mapping[str, SyncedLeg], events: Mapping[str, tuple[np.ndarray, GaitEvents]],
                params: PipelineParams) -> dict[str, OtherLeg]:
    """Per leg, the contralateral leg's mid-swing times and gaps (:func:`_leg_events`): what lets a leg's
    processing tell its gait strides from jumps (:mod:`pipeline.bilateral`)."""
    if set(events) != {"left", "right"}:
        return {}
    seen = {leg: OtherLeg(np.sort(synced[leg].prep.t_s[ev.ms]), tuple(synced[leg].prep.gaps_s))
            for leg, (_, ev) in events.items() if not synced[leg].clock_disagreement}
    for leg, other in (("left", "right"), ("right", "left")):
        if leg in seen:
            seen[leg] = dataclasses.replace(seen[leg], walking_swings_s=_walking_swings_s(
                synced[leg], events[leg][1], seen.get(other), params))
    return {leg: seen[other] for leg, other in (("left", "right"), ("right", "left")) if other in seen}


def _walking_swings_s(synced: SyncedLeg, ev: GaitEvents, other: OtherLeg | None, params: PipelineParams
                      ) -> np.ndarray | None:
    """The leg's mid-swing times [s] (sorted) at which its thigh was near upright
    (:func:`pipeline.posture.thigh_upright_at`), its upright learned from its strides that alternate with ``other``
    (gait); None without such strides. A seated or lying one-legged exercise swings a thigh far from upright."""
    prep = synced.prep
    ms = np.sort(ev.ms[ev.ms >= 0])
    gait = gait_strides(prep.t_s, ev.strides, ev.ms, other)
    upright = thigh_upright_at(prep, synced.axes, gait, ms, params.posture) if gait and other is not None else None
    return None if upright is None else prep.t_s[ms[upright]]


def _leg_input(synced: SyncedLeg, activity: str, params: PipelineParams | None,
               calibration: KneeCalibration | None = None, other: OtherLeg | None = None,
               events: tuple[np.ndarray, GaitEvents] | None = None) -> tuple[LegInput, RunningDiagnostics | None]:
    """The estimators' input for one synchronised leg: the running flow when declared or (``unknown``) detected
    running, else the walking flow. ``params`` None: the preset of the activity the leg is processed as; either
    tree takes the leg's calibrated standing flexion. ``events``: :func:`_leg_events` of this leg, if computed."""
    walking = _calibrated(params if params is not None else preset(activity), calibration)
    running = _calibrated(params if params is not None else RUNNING, calibration)
    cycles = detect_running(synced.prep, walking.running) if activity == "unknown" else None
    if activity == "running" or cycles is not None:
        return build_running_leg_input(synced.prep, running, cycles)
    return build_walking_leg_input(synced.prep, walking, axes=synced.axes, fit_gyr=synced.fit_gyr,
                                   thigh_fit=synced.thigh_fit, other=other, events=events), None


def _calibrated(params: PipelineParams, calibration: KneeCalibration | None) -> PipelineParams:
    """The parameter tree with the leg's measured standing flexion as its absolute zero (unchanged without one)."""
    if calibration is None:
        return params
    return dataclasses.replace(params, posture=dataclasses.replace(
        params.posture, standing_knee_deg=float(calibration.standing_knee_deg), standing_knee_measured=True))


def process_leg(leg: str, thigh: RawSensorStream, shank: RawSensorStream, activity: str = "walking",
                estimator: str = "auto", params: PipelineParams | None = None,
                calibration: KneeCalibration | None = None) -> LegResult:
    """Knee flexion and strides of one leg (:func:`process_session` for one thigh/shank pair)."""
    return _process_leg(leg, thigh, shank, activity, estimator, params, calibration)[0]


def _process_leg(leg: str, thigh: RawSensorStream, shank: RawSensorStream, activity: str, estimator: str,
                 params: PipelineParams | None, calibration: KneeCalibration | None,
                 synced: SyncedLeg | None = None, other: OtherLeg | None = None,
                 events: tuple[np.ndarray, GaitEvents] | None = None) -> tuple[LegResult, np.ndarray]:
    """:func:`process_leg` and the times [s] of every mid-swing peak of the leg (in bouts or not). ``synced``: the
    leg already synchronised; ``other``: the contralateral leg's swings (:func:`_other_legs`); ``events``: the
    leg's own gait events on ``synced`` (:func:`_leg_events`)."""
    if synced is None:
        synced = _synced(leg, thigh, shank, activity, params)
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore", RuntimeWarning)
        data, running = _leg_input(synced, activity, params, calibration, other, events)
        result = auto(data) if estimator == "auto" else single_estimator(data, estimator)
    clock_unknown = synced.clock_disagreement or _clock_runaway(data, corrected=synced.shank_drift_ppm is not None)
    # the session fit's low-passed gyros when the synchronisation kept them; else the raw ones (filtering the session
    # again cost as much as the check itself, and the windows' verdicts were the same on the tune seeds)
    fit_gyr = synced.fit_gyr or (synced.prep.gyr_thigh_rps, synced.prep.gyr_shank_rps)
    principal = data.activity == "running" and data.params.running.thigh_axis == "principal"  # as its axes were found
    mounting = check_mounting(synced.prep, synced.axes, fit_gyr, data.params.mounting, principal_thigh=principal)
    if data.activity == "walking":
        mounting = with_level_step(mounting, data, data.params.mounting, result.stance_levels_deg, result.standing)
    not_worn, handled = not_worn_spans_s(data, other, data.params.worn) if data.activity == "walking" else ([], [])
    leg_reasons = (("clock_disagreement",) if clock_unknown else ()) + (("mounting_changed",) if mounting.changed
                                                                         else ())
    # the thigh over the shank's swing: not judged where the two clocks' timing is unknown
    lowered = set() if clock_unknown else lowered_not_stepped(data.thigh_sag_dps, data.events.strides, data.fs_hz,
                                                              data.params.phases)
    strides = _strides(leg, data, result, leg_reasons, lowered)
    if _mostly_mismatched(strides, data.params.quality):
        strides = with_reason(strides, "leg_mismatch", data.params.quality)
    # a lifted leg lowered in place (marching) alternates like gait but anchors nothing: it is no step
    not_steps = {data.events.strides[k] for k in lowered}
    n_gait = len(data.running_cycles) if data.running_cycles else \
        sum(s not in not_steps for s in gait_strides(data.prep.t_s, data.events.strides, data.events.ms, other))
    diagnostics = dataclasses.replace(_diagnostics(data, synced, result, strides, running, calibration,
                                                   clock_unknown, n_gait), mounting=mounting,
                                      lowered_strides=len(lowered),
                                      not_worn_s=_rounded_spans(not_worn), handled_s=_rounded_spans(handled))
    return LegResult(leg=leg, fs_hz=data.fs_hz, t_s=data.prep.t_s, angle_deg=result.angle_deg,
                     estimator=result.estimator, strides=strides, gaps_s=list(data.prep.gaps_s),
                     walking_s=float(sum(s.duration_s for s in strides)), activity=data.activity,
                     diagnostics=diagnostics), data.prep.t_s[data.events.ms]


def _mostly_mismatched(strides: list[StrideMetrics], params: QualityParams) -> bool:
    """Whether ``params.leg_mismatch_share`` or more of the leg's strides fail ``go_cf_mismatch``."""
    failed = sum("go_cf_mismatch" in s.quality_reasons for s in strides)
    return len(strides) >= params.leg_mismatch_min_strides and failed >= params.leg_mismatch_share * len(strides)


def _strides(leg: str, data: LegInput, result: PolicyResult, leg_reasons: tuple[str, ...] = (),
             lowered: set[int] | frozenset[int] = frozenset()) -> list[StrideMetrics]:
    """Metrics of every stride whose angle is finite throughout, with the policy's choice for it and the data's
    own reasons (:mod:`pipeline.quality`: filled gaps and long bridges, unsteady bout edges, turns;
    ``leg_reasons``: those of every stride of the leg). ``lowered``: indices into ``data.events.strides`` of the
    strides that are no steps (:mod:`pipeline.stepping`), left out."""
    angle, t_s = result.angle_deg, data.prep.t_s
    events = data.events
    out: list[StrideMetrics] = []
    # non-finite samples counted by prefix sum: one pass instead of a test per stride
    bad_cum = np.concatenate(([0], np.cumsum(~np.isfinite(angle))))
    kept = [(s, c) for k, (s, c) in enumerate(zip(events.strides, result.choices, strict=True))
            if bad_cum[s[2] + 1] == bad_cum[s[0]] and k not in lowered]
    triples = [s for s, _ in kept]
    qp = data.params.quality
    # bridged holes long enough for the cubic to miss the swing-flexion rise (the shorter ones keep the peak)
    long_bridges = [(g0, g1) for g0, g1 in data.prep.bridged_s if g1 - g0 > qp.bridged_peak_s]
    gap = gap_reasons(t_s, data.prep.filled_s, angle, triples, bridged_s=long_bridges, peak_lead_s=qp.peak_lead_s,
                      short_fill_s=qp.filled_peak_s, trusted_fill_s=qp.trusted_fill_s)
    lobe = {int(h): k for k, h in enumerate(events.hs) if h >= 0}
    ks = [lobe[a] for a, _, _ in triples]
    swing_dps = data.shank_sag_dps[events.ms[np.asarray(ks, dtype=int) + 1]]
    edge = edge_reasons(triples, events.bout[np.asarray(ks, dtype=int)].tolist(), swing_dps)
    turn = turn_reasons(data.prep.gyr_thigh_rps, data.prep.gyr_shank_rps, data.fs_hz, triples, qp.max_turn_deg)
    values = stride_values_many(angle, t_s, triples, data.params.metrics)
    for (_, choice), g, e, u, v in zip(kept, gap, edge, turn, values, strict=True):
        extra = tuple(r for r in (*g, *e, *u, *leg_reasons) if r not in choice.reasons)
        reasons = (*choice.reasons, *extra)
        quality = min(float(choice.quality), stride_quality(reasons, qp)) if extra else float(choice.quality)
        out.append(StrideMetrics(leg=leg, index=len(out), estimator=choice.estimator, quality=quality,
                                 quality_reasons=reasons, activity=data.activity,
                                 fallback=choice.fallback, **v.__dict__))
    return out


def _clock_runaway(data: LegInput, corrected: bool) -> bool:
    """:func:`pipeline.sync.stride_clock_runaway` on the leg's mid-swing peaks in walking bouts; for a leg whose
    clocks nothing corrected, beyond what two crystals drift apart (``SyncParams.crystal_drift``)."""
    ev = data.events
    ms = ev.ms[(ev.ms >= 0) & (ev.bout >= 0)]
    sync = data.params.sync
    return stride_clock_runaway(data.prep.t_s, data.thigh_sag_dps, ms, data.fs_hz, sync,
                                limit=sync.max_drift if corrected else sync.crystal_drift)


def _diagnostics(data: LegInput, synced: SyncedLeg, result: PolicyResult, strides: list[StrideMetrics],
                 running: RunningDiagnostics | None, calibration: KneeCalibration | None,
                 clock_unknown: bool, n_gait: int) -> LegDiagnostics:
    axes, centres, events = data.axes, data.centres, data.events
    return LegDiagnostics(
        activity=data.activity, axis_rms_residual_dps=round(axes.rms_residual_dps, 2),
        axis_fit_samples=axes.n_samples, centre_rms_residual_mps2=round(centres.rms_residual_mps2, 3),
        shank_lag_ms=synced.shank_lag_ms, shank_drift_ppm=synced.shank_drift_ppm,
        absolute_reference=result.absolute_reference, standing_ref_deg=result.standing_ref_deg,
        bouts=int(events.bout.max() + 1) if events.bout.size else 0, bridged_gaps=data.prep.bridged_gaps,
        n_strides=len(strides), n_fallback=sum(1 for s in strides if s.fallback),
        gait_strides=n_gait,
        j1=tuple(np.round(axes.j1, 4).tolist()), j2=tuple(np.round(axes.j2, 4).tolist()),
        o1_m=tuple(np.round(centres.o1, 4).tolist()), o2_m=tuple(np.round(centres.o2, 4).tolist()),
        cf_shift_deg=result.cf_shift_deg, offset_median_deg=result.offset_median_deg,
        bridge_check_deg=result.bridge_check_deg, level_bridged=result.level_bridged,
        fallback_bridge_check_deg=result.fallback_bridge_check_deg, gravity_shift_deg=result.gravity_shift_deg,
        tau_s=None if result.tuning is None else result.tuning.tau_s, running=running,
        standing_knee_deg=data.params.posture.standing_knee_deg,
        level_source="calibration" if calibration is not None else "assumed",
        masked_implausible_samples=result.masked_implausible_samples,
        calibration_id=None if calibration is None else calibration.calibration_id,
        acc_offset_thigh_mps2=tuple(np.round(synced.prep.acc_offset_thigh_mps2, 3).tolist()),
        acc_offset_shank_mps2=tuple(np.round(synced.prep.acc_offset_shank_mps2, 3).tolist()),
        gyr_bias_thigh_dps=tuple(np.round(np.degrees(synced.prep.gyr_bias_thigh_rps), 2).tolist()),
        gyr_bias_shank_dps=tuple(np.round(np.degrees(synced.prep.gyr_bias_shank_rps), 2).tolist()),
        hinge_lean_deg=None if axes.lean_deg is None else tuple(round(x, 1) for x in axes.lean_deg),
        knee_axes_levelled=axes.leaning, clock_disagreement=clock_unknown,
        weight_shift_dps=_weight_shift(data),
        centre_heights_m=tuple(round(h, 4) for h in centre_heights_m(
            centres.o1, centres.o2, data.prep.acc_thigh_mps2, data.prep.acc_shank_mps2, data.prep.valid)))


def _weight_shift(data: LegInput) -> tuple[float, float] | None:
    """:func:`pipeline.assignment.weight_shift_dps` of a walking leg (rounded), None for running."""
    if data.activity != "walking":
        return None
    prep = data.prep
    shift = weight_shift_dps(prep.gyr_thigh_rps, prep.acc_thigh_mps2, prep.valid,
                             data.axes.j1, data.events.strides, data.params.assignment)
    return None if shift is None else (round(shift[0], 2), round(shift[1], 2))
