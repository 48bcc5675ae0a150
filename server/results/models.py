"""Processing results: one row per stride and the continuous knee angle trace of each leg."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import JSON, Boolean, DateTime, Float, ForeignKey, Index, Integer, LargeBinary, String, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column

from server.db import Base


class Stride(Base):
    """One stride of one leg of a processed session (value columns: :mod:`server.results.stride_record`)."""

    __tablename__ = "strides"
    __table_args__ = (
        UniqueConstraint("session_id", "leg", "index"),
        Index("ix_strides_patient_leg_time", "patient_id", "leg", "started_at"),
    )
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id", ondelete="CASCADE"))
    # Denormalised from the session so per-patient time queries need no join.
    patient_id: Mapped[str] = mapped_column(ForeignKey("patients.id", ondelete="CASCADE"))
    leg: Mapped[str] = mapped_column(String(5))
    index: Mapped[int] = mapped_column(Integer)
    started_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))  # absolute heel strike time
    t_start_s: Mapped[float] = mapped_column(Float)
    t_end_s: Mapped[float] = mapped_column(Float)
    duration_s: Mapped[float] = mapped_column(Float)
    t_toe_off_s: Mapped[float] = mapped_column(Float)
    stance_time_s: Mapped[float] = mapped_column(Float)
    swing_time_s: Mapped[float] = mapped_column(Float)
    stance_pct: Mapped[float] = mapped_column(Float)
    peak_swing_flexion_deg: Mapped[float] = mapped_column(Float)
    min_flexion_deg: Mapped[float] = mapped_column(Float)
    rom_deg: Mapped[float] = mapped_column(Float)
    stance_flexion_deg: Mapped[float] = mapped_column(Float)
    estimator: Mapped[str] = mapped_column(String(16))
    # What the stride was processed as (walking | running) and whether its angle came from the fallback of that
    # activity's primary estimator: both from the pipeline, never re-derived from the estimator name.
    activity: Mapped[str] = mapped_column(String(16), default="walking")
    fallback: Mapped[bool] = mapped_column(Boolean, default=False)
    quality: Mapped[float] = mapped_column(Float)
    quality_reasons: Mapped[list] = mapped_column(JSON, default=list)


class KneeAngleTrace(Base):
    """The continuous knee angle of one leg of one session, as binary arrays on a uniform grid:
    ``angle_deg`` float32 (N,) starting at ``t0_s`` with step ``1/fs_hz`` (NaN in gaps),
    ``estimator_codes`` uint8 (N,) indexing ``estimator_names``."""

    __tablename__ = "knee_angle_traces"
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True)
    leg: Mapped[str] = mapped_column(String(5), primary_key=True)
    t0_s: Mapped[float] = mapped_column(Float)
    fs_hz: Mapped[float] = mapped_column(Float)
    n: Mapped[int] = mapped_column(Integer)
    angle_deg: Mapped[bytes] = mapped_column(LargeBinary)
    estimator_codes: Mapped[bytes] = mapped_column(LargeBinary)
    estimator_names: Mapped[list] = mapped_column(JSON)
