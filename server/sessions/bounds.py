"""How much processing work a session may ask for, decided from its stored batches before any array is built.

The pipeline resamples each sensor onto a uniform grid from its first to its last timestamp at the declared
rate, whatever the number of samples. Two bounds keep that grid proportional to what was uploaded:

- span: no sensor may span more than ``max_session_s`` (``GAITMON_MAX_SESSION_S``);
- density: per sensor, grid points (span x rate) <= 2 x samples + one minute of samples
  (:data:`GRID_SLACK_S`), i.e. at least about half of the span beyond the first minute must hold samples.

A session breaking either is refused at ``/complete`` (422, session unchanged), fails processing with the
reason, and is not compared.
"""

from __future__ import annotations

from sqlalchemy import func, select
from sqlalchemy.orm import Session as DbSession

from server.sessions.models import Batch, SessionSensor

# Grid points allowed beyond twice the sample count, in seconds of the declared rate: covers short recordings
# and the packet loss of a normal session.
GRID_SLACK_S = 60.0
GRID_PER_SAMPLE = 2.0


def sensor_span_problem(sensor_id: str, n_samples: int, first_ms: float, last_ms: float, fs_hz: float,
                        max_session_s: float) -> str | None:
    """Why one sensor's samples would ask for an absurd processing grid, or None."""
    span_s = max(0.0, (last_ms - first_ms) / 1000.0)
    if span_s > max_session_s:
        return (f"sensor {sensor_id!r} spans {span_s:.0f} s, more than the maximum session duration of "
                f"{max_session_s:.0f} s")
    grid = span_s * fs_hz
    allowed = GRID_PER_SAMPLE * n_samples + GRID_SLACK_S * fs_hz
    if grid > allowed:
        return (f"sensor {sensor_id!r} has {n_samples} samples spread over {span_s:.0f} s at {fs_hz:g} Hz "
                f"({grid:.0f} grid points; at most {GRID_PER_SAMPLE:g} per sample plus {GRID_SLACK_S:g} s are "
                f"processed): its timestamps are inconsistent with its sample count")
    return None


def session_span_problem(db: DbSession, session_id: str, max_session_s: float) -> str | None:
    """The first sensor of the session whose stored batches break the bounds, with why; None if all are fine.

    One aggregate query: no batch is decoded.
    """
    rows = db.execute(
        select(Batch.sensor_id, func.sum(Batch.n_samples), func.min(Batch.t_first_ms), func.max(Batch.t_last_ms),
               SessionSensor.sample_rate_hz)
        .join(SessionSensor, (SessionSensor.session_id == Batch.session_id)
              & (SessionSensor.sensor_id == Batch.sensor_id))
        .where(Batch.session_id == session_id)
        .group_by(Batch.sensor_id, SessionSensor.sample_rate_hz)
        .order_by(Batch.sensor_id)
    ).all()
    for sensor_id, n, first_ms, last_ms, fs_hz in rows:
        problem = sensor_span_problem(sensor_id, int(n), float(first_ms), float(last_ms), float(fs_hz),
                                      max_session_s)
        if problem is not None:
            return problem
    return None
