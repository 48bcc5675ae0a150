"""``Content-Disposition`` for downloads (RFC 6266 with the RFC 5987 ``filename*`` parameter)."""

from __future__ import annotations

import re
from urllib.parse import quote

# Printable ASCII without the quote and backslash, which would need escaping inside a quoted-string.
_UNSAFE_ASCII = re.compile(r'[^\x20-\x7e]|["\\]')


def attachment(filename: str) -> str:
    """``attachment`` with an ASCII ``filename`` fallback (anything else replaced by ``_``) and the exact name
    as UTF-8 in ``filename*``: any text (CR/LF, non-latin-1, a lone surrogate) yields a valid header."""
    fallback = _UNSAFE_ASCII.sub("_", filename)
    exact = quote(filename.encode("utf-8", errors="replace"), safe="")
    return f"attachment; filename=\"{fallback}\"; filename*=UTF-8''{exact}"
