"""Long sessions chunk by chunk (pipeline/long_sessions.py): each stride once, the same strides and peaks as one
block, only bounded windows read, and exactly process_session below one chunk."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.long_sessions import ArraySource, process_source
from pipeline.params import WALKING, LongSessionParams
from pipeline.session import process_session
from pipeline.simulate import SimConfig, SimSession, simulate_session
from pipeline.types import RawSensorStream, SessionResult

# Three chunks of 4 min: long enough for several 40 s clock-lag windows per chunk (pipeline.sync), short enough
# for a fast test. The real chunk is 30 min (pipeline.params.LongSessionParams).
CHUNKING = LongSessionParams(chunk_s=240.0, overlap_s=20.0, full_rate_trace_s=0.0)


class RecordingSource(ArraySource):
    """An array source that remembers every window it was asked for."""

    def __init__(self, streams: list[RawSensorStream]) -> None:
        super().__init__(streams)
        self.asked: list[tuple[float, float]] = []

    def window(self, t0_s: float, t1_s: float) -> list[RawSensorStream]:
        self.asked.append((t0_s, t1_s))
        return super().window(t0_s, t1_s)


@pytest.fixture(scope="module")
def sim() -> SimSession:
    return simulate_session(SimConfig(pattern="normal", fs_hz=100.0, seed=7, duration_s=720.0,
                                      activities=("standing",), bout_strides=40))


@pytest.fixture(scope="module")
def runs(sim: SimSession) -> tuple[SessionResult, SessionResult, RecordingSource]:
    src = RecordingSource(sim.streams)
    return process_session(sim.streams), process_source(src, chunking=CHUNKING), src


def _nearest(starts: np.ndarray, t: float) -> int:
    return int(np.argmin(np.abs(starts - t)))


def test_chunk_edges_inside_gait(sim: SimSession) -> None:
    """The test means something only if strides straddle the chunk edges."""
    edges = np.linspace(*ArraySource(sim.streams).span_s(), 4)[1:-1]
    for leg in ("left", "right"):
        straddling = [s for s in sim.truth[leg].strides for e in edges if s.t_start_s < e < s.t_end_s]
        assert len(straddling) == len(edges)


def test_every_stride_once_and_as_in_one_block(runs) -> None:  # noqa: ANN001
    one, chunked, _ = runs
    assert set(chunked.legs) == set(one.legs) == {"left", "right"}
    for leg in one.legs:
        a, b = one.legs[leg].strides, chunked.legs[leg].strides
        ta, tb = np.array([s.t_start_s for s in a]), np.array([s.t_start_s for s in b])
        assert np.all(np.diff(tb) > 0.4), "a stride kept twice"
        assert len(b) == len(a) > 500
        assert [s.index for s in b] == list(range(len(b)))
        pairs = [(s, a[_nearest(ta, s.t_start_s)]) for s in b]
        assert max(abs(s.t_start_s - r.t_start_s) for s, r in pairs) < 0.05
        assert max(abs(s.t_end_s - r.t_end_s) for s, r in pairs) < 0.05
        diff = np.array([s.peak_swing_flexion_deg - r.peak_swing_flexion_deg for s, r in pairs])
        # per-chunk clock-lag and axis fits move a stride's peak by tenths of a degree (each chunk's lag here is
        # within ~0.5 ms of the true one, whose drift moves it by 8-9 ms over the 12 minutes)
        assert np.median(np.abs(diff)) < 0.6
        assert np.max(np.abs(diff)) < 2.0
        assert [s.estimator for s, _ in pairs] == [r.estimator for _, r in pairs]
        assert chunked.legs[leg].diagnostics.n_strides == len(b)
        assert chunked.legs[leg].walking_s == pytest.approx(one.legs[leg].walking_s, abs=0.5)


def test_only_bounded_windows_are_read(runs) -> None:  # noqa: ANN001
    _, _, src = runs
    assert len(src.asked) == 3
    assert all(np.isfinite(a) and np.isfinite(b) for a, b in src.asked)
    assert max(b - a for a, b in src.asked) <= CHUNKING.chunk_s + 2 * CHUNKING.overlap_s + 1e-6


def test_trace_bounded_on_one_grid(runs, sim: SimSession) -> None:  # noqa: ANN001
    one, chunked, _ = runs
    for leg in one.legs:
        lr, full = chunked.legs[leg], one.legs[leg]
        assert lr.fs_hz == pytest.approx(25.0)
        assert lr.t_s.size == lr.angle_deg.size == lr.estimator.size
        assert lr.t_s.size < full.t_s.size / 3
        assert np.allclose(np.diff(lr.t_s), 1 / lr.fs_hz)
        # the decimated trace follows the one-block angle (same samples, chunk-wise estimates)
        ref = np.interp(lr.t_s, full.t_s, full.angle_deg)
        ok = np.isfinite(ref) & np.isfinite(lr.angle_deg)
        assert ok.mean() > 0.8
        assert np.median(np.abs(lr.angle_deg[ok] - ref[ok])) < 1.0
        assert set(np.unique(lr.estimator[ok])) <= {"go", "cf"}


def test_trace_at_full_rate_up_to_an_hour(sim: SimSession) -> None:
    one = process_session(sim.streams)
    res = process_source(ArraySource(sim.streams), chunking=dataclasses.replace(CHUNKING, full_rate_trace_s=3600.0))
    for leg in one.legs:
        lr, full = res.legs[leg], one.legs[leg]
        assert lr.fs_hz == full.fs_hz
        assert np.allclose(np.diff(lr.t_s), 1 / lr.fs_hz)
        # one grid from the session's first sample: a few samples more than the leg's own grid, none fewer
        assert 0 <= lr.t_s.size - full.t_s.size <= 10
        ref = np.interp(lr.t_s, full.t_s, full.angle_deg)
        ok = np.isfinite(ref) & np.isfinite(lr.angle_deg)
        assert ok.mean() > 0.8
        assert np.median(np.abs(lr.angle_deg[ok] - ref[ok])) < 1.0


def test_shorter_than_a_chunk_is_process_session(sim: SimSession) -> None:
    src = RecordingSource(sim.streams)
    a = process_source(src, chunking=dataclasses.replace(CHUNKING, chunk_s=800.0))
    b = process_session(sim.streams)
    assert len(src.asked) == 1
    assert a.summary() == b.summary()
    for leg in b.legs:
        assert a.legs[leg].strides == b.legs[leg].strides
        assert np.array_equal(a.legs[leg].angle_deg, b.legs[leg].angle_deg, equal_nan=True)


def test_unknown_estimator_fails_before_any_chunk(sim: SimSession) -> None:
    src = RecordingSource(sim.streams)
    with pytest.raises(ValueError, match="estimator"):
        process_source(src, estimator="nope", chunking=CHUNKING)
    assert src.asked == []


def test_default_chunking_is_the_parameter_tree() -> None:
    assert WALKING.long_sessions.chunk_s >= 600.0
    assert WALKING.long_sessions.overlap_s > WALKING.phases.max_period_s


def test_chunk_without_usable_data_is_a_warning(sim: SimSession) -> None:
    """A stretch with no samples of one leg (sensor off) leaves that chunk's strides out, not the session."""
    t0, t1 = ArraySource(sim.streams).span_s()
    cut = []
    for s in sim.streams:
        if s.leg == "right":
            keep = (s.t_s < t0 + 215) | (s.t_s > t0 + 505)  # the whole window of the middle chunk
            s = dataclasses.replace(s, t_s=s.t_s[keep], gyr=s.gyr[keep], acc=s.acc[keep])
        cut.append(s)
    res = process_source(ArraySource(cut), chunking=CHUNKING)
    right = res.legs["right"].strides
    assert right and not any(t0 + 215 < s.t_start_s < t0 + 505 for s in right)
    assert len(res.legs["left"].strides) > 500
    assert any(w.startswith("00:04:0") and "right leg: no result" in w for w in res.warnings), res.warnings


def test_a_chunk_without_gait_withholds_only_its_part_of_the_trace(sim: SimSession) -> None:
    """The sensors lie still through the middle chunk's whole window: that chunk has no gait to anchor its axes, so
    its part of the trace is withheld; the leg, shown in the other chunks, is not marked withheld."""
    t0, _ = ArraySource(sim.streams).span_s()
    rng = np.random.default_rng(0)
    still = []
    for s in sim.streams:
        m = (s.t_s >= t0 + 215) & (s.t_s < t0 + 505)
        gyr, acc = s.gyr.copy(), s.acc.copy()
        gyr[m] = 0.002 * rng.standard_normal((int(m.sum()), 3))
        acc[m] = s.acc[0] + 0.02 * rng.standard_normal((int(m.sum()), 3))
        still.append(dataclasses.replace(s, gyr=gyr, acc=acc))
    res = process_source(ArraySource(still), chunking=CHUNKING)
    assert sum("no knee angle" in w for w in res.warnings) == 2
    for lr in res.legs.values():
        assert lr.diagnostics.trace_withheld is None and lr.diagnostics.gait_strides > 0
        middle = (lr.t_s > t0 + 250) & (lr.t_s < t0 + 470)
        assert np.isnan(lr.angle_deg[middle]).all()
        assert np.isfinite(lr.angle_deg[~middle]).mean() > 0.9


def test_a_mounting_change_in_one_chunk_speaks_for_the_leg() -> None:
    """Each chunk fits its own axes: only the chunk holding the turn sees two mountings; its strides are out of
    trends, the others' are not, and the leg's diagnostics report the change."""
    sim = simulate_session(SimConfig(pattern="normal", fs_hz=100.0, seed=7, duration_s=720.0,
                                     activities=("standing",), bout_strides=40, remount_segment="shank",
                                     remount_deg=30.0, remount_axis="long"))
    res = process_source(ArraySource(sim.streams), chunking=CHUNKING)
    left = res.legs["left"]
    assert left.diagnostics.mounting is not None and left.diagnostics.mounting.changed
    flagged = [s for s in left.strides if "mounting_changed" in s.quality_reasons]
    t0, _ = ArraySource(sim.streams).span_s()
    assert flagged and all(t0 + 215 < s.t_start_s < t0 + 505 for s in flagged)  # the middle chunk's window
    assert any("mounting_changed" not in s.quality_reasons and s.quality >= 0.5 for s in left.strides)
    assert not any("mounting_changed" in s.quality_reasons for s in res.legs["right"].strides)


def test_sensors_taken_off_are_one_span_over_the_chunks() -> None:
    """The left leg's sensors lie on a table for the second half of a chunked session: every chunk after the
    removal cuts its part, and the leg's diagnostics hold one span from the removal to the end (chunks overlap)."""
    sim = simulate_session(SimConfig(pattern="normal", fs_hz=100.0, seed=7, duration_s=720.0,
                                     activities=("standing",), bout_strides=40, off_body="left"))
    res = process_source(ArraySource(sim.streams), chunking=CHUNKING)
    left = res.legs["left"]
    t0, _ = ArraySource(sim.streams).span_s()
    off_s = t0 + sim.info["sensors"]["L-thigh"]["off_body"]["at_s"]
    (a, b), = left.diagnostics.not_worn_s
    assert off_s - 10.0 < a <= off_s + 0.5 and b > t0 + sim.duration_s - 1.0
    assert not np.isfinite(left.angle_deg[left.t_s > off_s + 0.5]).any()
    assert all(s.t_end_s < off_s + 0.5 for s in left.strides)
    assert any(s.quality >= 0.5 for s in left.strides)  # pieces of minutes vouch for their mounting
    assert res.legs["right"].diagnostics.not_worn_s == ()
