"""Opaque keyset cursors over (created_at, id) for the list endpoints."""

from __future__ import annotations

import base64
import binascii
import json
from datetime import datetime
from typing import Any

from sqlalchemy import ColumnElement, and_, or_
from sqlalchemy.orm import InstrumentedAttribute

from server.errors import invalid


def encode_cursor(created_at: datetime, row_id: str) -> str:
    """The cursor of the row after which the next page starts."""
    raw = json.dumps([created_at.isoformat(), row_id]).encode()
    return base64.urlsafe_b64encode(raw).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[datetime, str]:
    """The (created_at, id) a cursor encodes, or a 400 problem for anything this API did not hand out."""
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
