"""SQLAlchemy 2 models. Every change here needs an Alembic migration in ``migrations/versions``."""

from __future__ import annotations

import uuid
from datetime import UTC, datetime

from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship


def new_id() -> str:
    return uuid.uuid4().hex


def utcnow() -> datetime:
    return datetime.now(UTC)


class Base(DeclarativeBase):
    pass


class Clinician(Base):
    __tablename__ = "clinicians"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200))
    email: Mapped[str | None] = mapped_column(String(320))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class Token(Base):
    """Opaque bearer token; only its SHA-256 is stored."""

    __tablename__ = "tokens"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    role: Mapped[str] = mapped_column(String(16))  # admin | clinician | device
    name: Mapped[str | None] = mapped_column(String(200))
    clinician_id: Mapped[str | None] = mapped_column(ForeignKey("clinicians.id", ondelete="CASCADE"), index=True)
    patient_id: Mapped[str | None] = mapped_column(ForeignKey("patients.id", ondelete="CASCADE"), index=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))


class Patient(Base):
    __tablename__ = "patients"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    clinician_id: Mapped[str | None] = mapped_column(ForeignKey("clinicians.id", ondelete="SET NULL"), index=True)
    external_id: Mapped[str | None] = mapped_column(String(200))
    display_name: Mapped[str | None] = mapped_column(String(200))
    affected_leg: Mapped[str | None] = mapped_column(String(5))
    timezone: Mapped[str] = mapped_column(String(64), default="UTC")
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class Session(Base):
    __tablename__ = "sessions"
    __table_args__ = (UniqueConstraint("patient_id", "client_session_id"),)
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    patient_id: Mapped[str] = mapped_column(ForeignKey("patients.id", ondelete="CASCADE"), index=True)
    client_session_id: Mapped[str] = mapped_column(String(200))
    started_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    activity: Mapped[str] = mapped_column(String(16), default="walking")
    # receiving | queued | processing | done | failed
    status: Mapped[str] = mapped_column(String(16), default="receiving", index=True)
    error: Mapped[str | None] = mapped_column(Text)
    algorithm_version: Mapped[str | None] = mapped_column(String(32))
    summary: Mapped[dict | None] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    completed_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    processed_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    # Claim of the job runner working on it; a stale heartbeat means the worker died.
    worker_id: Mapped[str | None] = mapped_column(String(64))
    heartbeat_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    attempts: Mapped[int] = mapped_column(Integer, default=0)

    sensors: Mapped[list[SessionSensor]] = relationship(
        back_populates="session", cascade="all, delete-orphan", passive_deletes=True,
        order_by="SessionSensor.sensor_id",
    )


class SessionSensor(Base):
    __tablename__ = "session_sensors"
    __table_args__ = (UniqueConstraint("session_id", "sensor_id"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id", ondelete="CASCADE"))
    sensor_id: Mapped[str] = mapped_column(String(64))
    leg: Mapped[str] = mapped_column(String(5))
    segment: Mapped[str] = mapped_column(String(5))
    sample_rate_hz: Mapped[float] = mapped_column(Float)
    gyro_unit: Mapped[str] = mapped_column(String(8))
    acc_unit: Mapped[str] = mapped_column(String(8))
    session: Mapped[Session] = relationship(back_populates="sensors")


class Batch(Base):
    """One BLE batch of one sensor. Samples are stored as little-endian binary arrays:
    ``t_ms`` float64 (N,), ``gyro`` and ``acc`` float32 (N, 3) row-major, in the declared units."""

    __tablename__ = "batches"
    __table_args__ = (UniqueConstraint("session_id", "sensor_id", "seq"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id", ondelete="CASCADE"))
    sensor_id: Mapped[str] = mapped_column(String(64))
    seq: Mapped[int] = mapped_column(Integer)
    t0_ms: Mapped[float] = mapped_column(Float)
    n_samples: Mapped[int] = mapped_column(Integer)
    t_first_ms: Mapped[float] = mapped_column(Float)
    t_last_ms: Mapped[float] = mapped_column(Float)
    content_sha256: Mapped[str] = mapped_column(String(64))
    t_ms: Mapped[bytes] = mapped_column(LargeBinary)
    gyro: Mapped[bytes] = mapped_column(LargeBinary)
    acc: Mapped[bytes] = mapped_column(LargeBinary)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class Stride(Base):
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
