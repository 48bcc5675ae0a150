"""pipeline.strapdown: orientations through cycles from the gyro alone, and the turn over each cycle."""

from __future__ import annotations

import numpy as np

from pipeline.strapdown import chained_frames, cycle_blocks, cycle_turn_deg, rotate, rotate_padded

FS = 100.0


def test_a_steady_turn_is_integrated_to_its_angle_whatever_the_axis() -> None:
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    gyr = np.tile(np.deg2rad(90.0) * axis, (301, 1))  # 90 deg/s for 3 s
    turn = cycle_turn_deg(gyr, FS, np.array([0, 100, 250]), np.array([100, 250, 300]))
    np.testing.assert_allclose(turn, [90.0, 135.0, 45.0], atol=1e-6)
    # an angle, not a winding count: three quarters of a turn one way is a quarter the other
    assert abs(cycle_turn_deg(gyr, FS, np.array([0]), np.array([300]))[0] - 90.0) < 1e-6
    f = chained_frames(gyr, FS, np.array([0, 101]), np.array([101, 151]))
    assert f.owner.tolist() == [0] * 101 + [1] * 50 and f.idx.tolist() == list(range(151))
    # the last sample's frame, seen from the first: turned by 90 deg about the axis
    e = np.cross(axis, [1.0, 0.0, 0.0])
    e /= np.linalg.norm(e)
    q_last = f.q[:, 100, 0][None, :]
    turned = rotate(q_last, e[None, :])[0]
    # a quarter turn about the axis, in its positive sense (right-hand rule)
    np.testing.assert_allclose(turned, np.cross(axis, e), atol=1e-6)
    # the padded grid's rotation is the same; past the shorter cycle's end its last frame is held
    v = np.random.default_rng(1).standard_normal((151, 3))
    padded = rotate_padded(f.q, f.padded(v))[:, f.pos, f.owner].T
    np.testing.assert_allclose(padded, rotate(f.q[:, f.pos, f.owner].T, v), atol=1e-12)
    np.testing.assert_allclose(f.q[:, 50:, 1], f.q[:, 49:50, 1] * np.ones((4, 51)), atol=1e-15)


def test_a_swing_that_returns_turns_by_nothing_a_heading_change_by_its_angle() -> None:
    t = np.arange(101) / FS  # one 1 s cycle, end sample included
    swing = np.deg2rad(200.0) * np.sin(2 * np.pi * t)[:, None] * np.array([0.0, 1.0, 0.0])  # back where it began
    heading = np.deg2rad(60.0) * np.array([0.0, 0.0, 1.0]) * np.ones((t.size, 1))  # 60 deg over the cycle
    turn = cycle_turn_deg(np.vstack([swing, swing + heading]), FS, np.array([0, 101]), np.array([100, 201]))
    assert turn[0] < 0.5
    # the swing and the heading do not commute, so the body's 60 deg reach the sensor with a small error only
    assert abs(turn[1] - 60.0) < 6.0, turn


def test_cycles_are_grouped_by_length_into_bounded_grids_and_the_groups_change_nothing() -> None:
    rng = np.random.default_rng(2)
    lengths = rng.integers(80, 140, size=3000)
    lengths[7] = 2000  # one long cycle may not blow up the grid of all the others
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    ends = starts + lengths
    groups = cycle_blocks(starts, ends, max_cells=1 << 16)
    assert sorted(np.concatenate(groups).tolist()) == list(range(3000))
    for g in groups:
        assert g.size == 1 or g.size * lengths[g].max() <= 1 << 16
    gyr = rng.standard_normal((int(ends[-1]), 3))
    together = cycle_turn_deg(gyr, FS, starts, ends - 1)
    alone = np.array([cycle_turn_deg(gyr, FS, starts[k:k + 1], ends[k:k + 1] - 1)[0] for k in range(0, 3000, 97)])
    np.testing.assert_allclose(together[::97], alone, atol=1e-9)
