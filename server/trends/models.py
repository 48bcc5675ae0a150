"""Per session, leg and activity summaries the trend queries aggregate from (kept by :mod:`server.trends.summaries`).

A one-year daily trend reads ~365 small rows instead of ~365,000 strides: each row holds the included values of one
metric of one session, leg and activity as a compact float32 array plus their count, mean, sd and median.
"""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import DateTime, Float, ForeignKey, Index, Integer, LargeBinary, String, Text
from sqlalchemy.orm import Mapped, mapped_column

from server.db import Base
from server.utc import utcnow


class TrendSessionLeg(Base):
    """Counts of one leg and activity of one processed session: strides, quality exclusions, fallbacks, gaps, time."""

    __tablename__ = "trend_session_legs"
    __table_args__ = (Index("ix_trend_session_legs_patient_time", "patient_id", "activity", "started_at"),)
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True)
    leg: Mapped[str] = mapped_column(String(5), primary_key=True)
    activity: Mapped[str] = mapped_column(String(16), primary_key=True)  # walking | running, never pooled
    # Denormalised from the session so the per-patient time-range scan needs no join.
    patient_id: Mapped[str] = mapped_column(ForeignKey("patients.id", ondelete="CASCADE"))
    started_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    n_strides: Mapped[int] = mapped_column(Integer)
    n_low_quality: Mapped[int] = mapped_column(Integer)
    n_fallback: Mapped[int] = mapped_column(Integer)  # strides whose angle came from a fallback estimator
    n_gaps: Mapped[int] = mapped_column(Integer)
    walking_s: Mapped[float] = mapped_column(Float)
    # Quality-passing strides with a knee angle outside its plausibility limits (any angle metric).
    n_implausible: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    # Strides the leg should have given: the most strides any leg of the session gave in this activity (both legs
    # walk the same cycles), or, for a lone leg whose sensors stopped early, its strides scaled up to full coverage.
    n_expected: Mapped[int | None] = mapped_column(Integer)
    # Share of the session's recording span that both sensors of this leg delivered data for (None: unknown).
    coverage: Mapped[float | None] = mapped_column(Float)
    algorithm_version: Mapped[str | None] = mapped_column(String(32))
    refreshed_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class TrendMetricValues(Base):
    """The included (quality-passing, plausible) values of one metric of one session, leg and activity.

    ``values`` is little-endian float32, ascending (quantiles of one session need no sort); ``n_implausible``
    counts quality-passing strides outside the metric's plausibility limits (low-quality strides are counted
    once, on :class:`TrendSessionLeg`).
    """

    __tablename__ = "trend_metric_values"
    __table_args__ = (
        Index("ix_trend_metric_values_patient_metric_leg_time", "patient_id", "metric", "leg", "activity",
              "started_at"),
    )
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True)
    leg: Mapped[str] = mapped_column(String(5), primary_key=True)
    activity: Mapped[str] = mapped_column(String(16), primary_key=True)
    metric: Mapped[str] = mapped_column(String(40), primary_key=True)
    patient_id: Mapped[str] = mapped_column(ForeignKey("patients.id", ondelete="CASCADE"))
    started_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    n_included: Mapped[int] = mapped_column(Integer)
    n_implausible: Mapped[int] = mapped_column(Integer)
    mean: Mapped[float | None] = mapped_column(Float)
    sd: Mapped[float | None] = mapped_column(Float)
    median: Mapped[float | None] = mapped_column(Float)
    p10: Mapped[float | None] = mapped_column(Float)
    p90: Mapped[float | None] = mapped_column(Float)
    values: Mapped[bytes] = mapped_column(LargeBinary)


class AttentionEvidence(Base):
    """The attention flags of one patient as of their latest processed session, for every preset (kept by
    :func:`server.trends.attention.evidence.refresh_patient` whenever a session of the patient is processed).

    ``flags`` is the JSON text {preset: {"legs": {leg: flag | null}, "sensor": flag | null}}, decoded only for the
    returned page; ``flag_index`` lists every flag as ``preset|leg|kind|severity|effect`` (leg ``*`` for the
    patient-level sensor flag), ``;``-separated, so ranking a thousand patients parses short strings only;
    ``legs``: the legs with data, comma-separated. ``silent`` depends on the clock and is judged per request from
    ``as_of`` (the latest processed session) and the patient's sessions still pending. ``n_sessions`` and
    ``first_session_at`` are the patient's exposure (processed sessions); ``rules_version`` is the version of the
    rules the flags were computed with (:data:`server.trends.attention.evidence.RULES_VERSION`), so a rule change
    is backfilled without a migration.
    """

    __tablename__ = "attention_evidence"
    patient_id: Mapped[str] = mapped_column(ForeignKey("patients.id", ondelete="CASCADE"), primary_key=True)
    as_of: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    legs: Mapped[str] = mapped_column(String(32))
    flag_index: Mapped[str] = mapped_column(Text)
    flags: Mapped[str] = mapped_column(Text)
    n_sessions: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    first_session_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    rules_version: Mapped[str | None] = mapped_column(String(16))
    refreshed_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
