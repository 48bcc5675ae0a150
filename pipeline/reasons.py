"""The per-stride quality reason codes and what each means: the one list that the API's documentation, the pages'
words and the tests read. A stride's ``reasons`` come from :mod:`pipeline.policy` (the estimate) and
:mod:`pipeline.quality` (the data); what each costs is ``pipeline.params.QualityParams``."""

from __future__ import annotations

REASONS: dict[str, str] = {
    "assumed_level": "the absolute level rests on the assumed standing knee flexion "
                     "(PostureParams.standing_knee_deg); no calibration was recorded for this leg",
    "no_absolute_reference": "no quiet standing in the session to anchor the angle's zero",
    "few_quiet_samples": "only a few quiet samples anchor the angle's zero",
    "go_level": "running without quiet standing: the level is the gyroscope-only estimate's (zero at the "
                "straightest moment of the stride), which a running knee never reaches (out of trends)",
    "no_go_estimate": "the gyroscope-only estimate is incomplete in the stride",
    "no_zero_crossing": "no zero-velocity point in the stride to reset the gyroscope's drift",
    "drift": "the gyroscope-only estimate drifted beyond its limit",
    "saturation": "a sensor reading hit its full-scale limit",
    "level_wander": "running: the filter's level against the gyroscope-only estimate's strays from the leg's usual "
                    "one in this stride (RunningParams.level_wander_deg): the accelerometer updates dragged it "
                    "(out of trends)",
    "go_cf_mismatch": "the gyroscope-only and complementary-filter estimates disagree in shape (out of trends)",
    "leg_mismatch": "most of the leg's strides fail the gyroscope-only / complementary-filter agreement "
                    "(QualityParams.leg_mismatch_share): a fault common to the whole leg (its thigh-shank timing or "
                    "axes) that the check catches only where it shows most, so none of its strides is vouched for "
                    "(out of trends)",
    "cf_fallback": "the complementary filter was used instead of the gyroscope-only estimate",
    "bridged_gap": "a short data gap inside the stride was bridged",
    "event_in_gap": "a heel strike or toe-off fell inside a bridged gap",
    "peak_in_gap": "the swing peak, the stance minimum or the rise to the peak fell inside a modelled gap "
                   "(out of trends)",
    "long_gap": "a gap longer than half a stride (QualityParams.trusted_fill_s) inside the stride was filled from "
                "the neighbouring strides: a whole swing or stance phase may be theirs (out of trends)",
    "bout_edge": "first or last stride of a walking bout",
    "turning": "the body turned by more than QualityParams.max_turn_deg over the stride (a turn, a pivot, a shuffle "
               "step): not the straight gait that trends compare (out of trends)",
    "side_in_doubt": "both thighs shift their weight in early stance the way the other leg's would: the left and "
                     "right labels of the four sensors (or of the two thighs) look swapped, so the stride may "
                     "belong to the other knee (out of trends)",
    "mounting_changed": "a sensor's mounting changed during the session: the knee axis in its frame moved between "
                        "the windows before a point in time and those after it, or its level stepped there in quiet "
                        "standing and in the strides alike (MountingParams), so one set of axes and one level do not "
                        "fit the whole session (out of trends)",
    "sensors_handled": "the leg's sensors were handled during the session (taken off, put back: pipeline.worn) and "
                       "the stretch this stride belongs to is too short to check on its own that the sensors kept "
                       "one mounting in it (WornParams.trusted_piece_s) (out of trends)",
    "clock_disagreement": "the thigh and shank clocks drift apart in a way no credible clock rate explains "
                          "(SyncParams.max_drift, max_line_drift): the timing between the two segments, and so the "
                          "angle, is unknown (out of trends)",
}
"""Code -> meaning. ``(out of trends)``: the reason alone keeps the stride below the trend threshold."""
