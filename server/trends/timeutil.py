"""Patient-local calendar arithmetic: buckets are days/weeks in the patient's time zone, storage is UTC."""

from __future__ import annotations

from datetime import UTC, date, datetime, time, timedelta
from typing import Literal
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from server.utc import as_utc

Bucket = Literal["day", "week"]


def zone(name: str | None) -> ZoneInfo:
    """The patient's time zone (UTC when unknown)."""
    try:
        return ZoneInfo(name or "UTC")
    except (ZoneInfoNotFoundError, ValueError, OSError):
        return ZoneInfo("UTC")


def local_date(dt: datetime, tz: ZoneInfo) -> date:
    """The local calendar date of a stored instant."""
    return as_utc(dt).astimezone(tz).date()


def bucket_date(day: date, bucket: Bucket) -> date:
    """The first local day of the bucket: the day itself, or the Monday of its ISO week."""
    return day - timedelta(days=day.weekday()) if bucket == "week" else day


def local_midnight(day: date, tz: ZoneInfo) -> datetime:
    """Start of a local day as an aware datetime (correct offset on DST change days)."""
    return datetime.combine(day, time(0, 0), tzinfo=tz)


def bucket_bounds(start_day: date, bucket: Bucket, tz: ZoneInfo) -> tuple[datetime, datetime]:
    """The UTC-aware start and end of a bucket in the patient's zone."""
    days = 7 if bucket == "week" else 1
    return local_midnight(start_day, tz), local_midnight(start_day + timedelta(days=days), tz)


def parse_bound(value: str, tz: ZoneInfo, *, end: bool) -> datetime:
    """A ``from``/``to`` query value: a date (a local day of the patient; ``to`` includes that whole day) or an ISO
    8601 date-time (without offset it is local time of the patient). Returns UTC. Raises ValueError."""
    value = value.strip()
    try:
        if len(value) == 10:
            day = date.fromisoformat(value)
            return local_midnight(day + timedelta(days=1) if end else day, tz).astimezone(UTC)
        dt = datetime.fromisoformat(value.replace("Z", "+00:00"))
        if dt.tzinfo is None:
            dt = dt.replace(tzinfo=tz)
        return dt.astimezone(UTC)
    except OverflowError as exc:  # the year 1 or 9999 moved past the calendar by the patient's offset
        raise ValueError(f"{value!r} is out of the supported date range") from exc

