"""Patients: who is monitored, by which clinician, in which time zone."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import DateTime, Float, ForeignKey, String
from sqlalchemy.orm import Mapped, mapped_column

from server.db import Base, new_id
from server.utc import utcnow


class Patient(Base):
    """A monitored patient, owned by a clinician."""

    __tablename__ = "patients"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    clinician_id: Mapped[str | None] = mapped_column(ForeignKey("clinicians.id", ondelete="SET NULL"), index=True)
    external_id: Mapped[str | None] = mapped_column(String(200))
    display_name: Mapped[str | None] = mapped_column(String(200))
    affected_leg: Mapped[str | None] = mapped_column(String(5))
    timezone: Mapped[str] = mapped_column(String(64), default="UTC")
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    # The monitoring schedule the clinician prescribed; the attention list's ``silent`` flag follows it when set.
    prescribed_sessions_per_week: Mapped[float | None] = mapped_column(Float)
