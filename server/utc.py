"""Time in the service: every stored instant is aware UTC."""

from __future__ import annotations

from datetime import UTC, datetime


def utcnow() -> datetime:
    """The current instant, aware UTC."""
    return datetime.now(UTC)


def as_utc(dt: datetime) -> datetime:
    """An aware UTC instant from a stored one (SQLite hands back naive datetimes, which are UTC)."""
    return dt.replace(tzinfo=UTC) if dt.tzinfo is None else dt.astimezone(UTC)
