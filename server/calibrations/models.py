"""Knee calibrations: one measured standing knee flexion of one leg of a patient, with when and how it was taken."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import DateTime, Float, ForeignKey, Index, String, Text
from sqlalchemy.orm import Mapped, mapped_column

from server.db import Base, new_id
from server.utc import utcnow


class KneeCalibration(Base):
    """A standing knee flexion measured for one leg (goniometer or guided trial), valid from ``measured_at``."""

    __tablename__ = "knee_calibrations"
    __table_args__ = (Index("ix_knee_calibrations_patient_leg_time", "patient_id", "leg", "measured_at"),)
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    patient_id: Mapped[str] = mapped_column(ForeignKey("patients.id", ondelete="CASCADE"))
    leg: Mapped[str] = mapped_column(String(5))
    standing_knee_deg: Mapped[float] = mapped_column(Float)
    measured_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    method: Mapped[str] = mapped_column(String(16))
    note: Mapped[str | None] = mapped_column(Text)
    # the token that recorded it (no foreign key: the audit trail outlives a revoked or deleted token)
    recorded_by_token_id: Mapped[str | None] = mapped_column(String(32))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
