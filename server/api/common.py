"""Shared pieces of the routers: dependency aliases, time zones on output, opaque keyset cursors."""

from __future__ import annotations

import base64
import binascii
import json
import math
from datetime import UTC, datetime
from typing import Annotated, Any

from fastapi import Depends, Request
from sqlalchemy import ColumnElement, and_, or_
from sqlalchemy.orm import InstrumentedAttribute
from sqlalchemy.orm import Session as DbSession

from server.auth import Principal, current_principal
from server.config import Settings
from server.db import get_db
from server.errors import invalid

Db = Annotated[DbSession, Depends(get_db)]
Caller = Annotated[Principal, Depends(current_principal)]


async def get_app_settings(request: Request) -> Settings:
    return request.app.state.settings


AppSettings = Annotated[Settings, Depends(get_app_settings)]


def aware(dt: datetime | None) -> datetime | None:
    """SQLite returns naive datetimes; every stored time is UTC, so say so on output."""
    if dt is None:
        return None
    return dt if dt.tzinfo is not None else dt.replace(tzinfo=UTC)


def finite_or_none(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def encode_cursor(created_at: datetime, row_id: str) -> str:
    raw = json.dumps([created_at.isoformat(), row_id]).encode()
    return base64.urlsafe_b64encode(raw).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[datetime, str]:
    try:
        raw = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4))
        created, row_id = json.loads(raw)
        # The stored form is kept (naive on SQLite, aware on PostgreSQL) so the comparison matches the column.
        return datetime.fromisoformat(created), str(row_id)
    except (ValueError, TypeError, binascii.Error, json.JSONDecodeError) as exc:
        raise invalid("cursor", "not a cursor returned by this API", status=400) from exc


def after_cursor(created_col: InstrumentedAttribute[Any], id_col: InstrumentedAttribute[Any],
                 cursor: str) -> ColumnElement[bool]:
    """Keyset condition: rows strictly after the cursor in (created_at, id) order."""
    created, row_id = decode_cursor(cursor)
    return or_(created_col > created, and_(created_col == created, id_col > row_id))
