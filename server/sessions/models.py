"""Recording sessions, their sensors and the raw batches they received."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import JSON, DateTime, Float, ForeignKey, Integer, LargeBinary, String, Text, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column, relationship

from server.db import Base, new_id
from server.enums import SessionStatus
from server.utc import utcnow


class Session(Base):
    """One recording session of a patient and where its processing stands."""

    __tablename__ = "sessions"
    __table_args__ = (UniqueConstraint("patient_id", "client_session_id"),)
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    patient_id: Mapped[str] = mapped_column(ForeignKey("patients.id", ondelete="CASCADE"), index=True)
    client_session_id: Mapped[str] = mapped_column(String(200))
    started_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    activity: Mapped[str] = mapped_column(String(16), default="walking")
    # receiving | queued | processing | done | failed
    status: Mapped[str] = mapped_column(String(16), default=SessionStatus.receiving, index=True)
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
    """One declared sensor of a session: leg, segment, rate and units."""

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
