"""The stride record of the pipeline -> service contract, declared once from :class:`pipeline.types.StrideValues`.

The ORM columns (:class:`server.results.models.Stride`), the response schema (:mod:`server.results.schemas`), the
CSV export and the test factory all take their value fields from ``STRIDE_VALUE_FIELDS``; a test asserts the ORM
and the schema match it, so a field added to the pipeline type cannot be silently dropped on the way to the API.
"""

from __future__ import annotations

from dataclasses import fields

from pipeline.types import StrideMetrics, StrideValues

# Unit of a value field from its name's suffix (the pipeline's naming rule: units in names).
_UNIT_SUFFIXES = (("_deg", "deg"), ("_pct", "%"), ("_s", "s"))


def unit_of(name: str) -> str:
    """The unit a stride value field's name declares."""
    for suffix, unit in _UNIT_SUFFIXES:
        if name.endswith(suffix):
            return unit
    raise ValueError(f"stride field {name!r} names no unit")


STRIDE_VALUE_FIELDS: tuple[str, ...] = tuple(f.name for f in fields(StrideValues))
STRIDE_UNITS: dict[str, str] = {name: unit_of(name) for name in STRIDE_VALUE_FIELDS}
# The per-stride fields beyond the values, as the pipeline declares them.
STRIDE_META_FIELDS: tuple[str, ...] = tuple(
    f.name for f in fields(StrideMetrics) if f.name not in STRIDE_VALUE_FIELDS)
# What the service stores of every stride besides its values (leg and index are part of its key).
STORED_FLOATS: tuple[str, ...] = (*STRIDE_VALUE_FIELDS, "quality")
