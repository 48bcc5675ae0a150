"""The stride record is declared once (pipeline.types.StrideValues): ORM, response schema, CSV and the test
factory all carry exactly its value fields, plus the per-stride facts the pipeline adds."""

from __future__ import annotations

from dataclasses import fields
from datetime import UTC, datetime

from sqlalchemy import Float

from pipeline.types import StrideMetrics, StrideValues
from server.results.models import Stride
from server.results.schemas import StrideOut
from server.results.stride_record import STRIDE_META_FIELDS, STRIDE_UNITS, STRIDE_VALUE_FIELDS
from server.trends.exports import CSV_COLUMNS, VALUE_COLUMNS
from tests.support.seed import stride_rows


def test_value_fields_are_the_pipelines_and_each_names_its_unit() -> None:
    assert tuple(f.name for f in fields(StrideValues)) == STRIDE_VALUE_FIELDS
    assert set(STRIDE_UNITS) == set(STRIDE_VALUE_FIELDS) and set(STRIDE_UNITS.values()) <= {"s", "%", "deg"}
    assert {"activity", "fallback", "estimator", "quality"} <= set(STRIDE_META_FIELDS)
    assert set(STRIDE_META_FIELDS) == {f.name for f in fields(StrideMetrics)} - set(STRIDE_VALUE_FIELDS)


def test_orm_columns_carry_every_value_and_per_stride_fact() -> None:
    columns = Stride.__table__.c
    for name in STRIDE_VALUE_FIELDS:
        assert isinstance(columns[name].type, Float), name
    assert set(STRIDE_META_FIELDS) <= set(columns.keys())


def test_response_schema_and_csv_carry_every_value_field() -> None:
    schema = list(StrideOut.model_fields)
    assert [f for f in schema if f in STRIDE_VALUE_FIELDS] == list(STRIDE_VALUE_FIELDS)
    assert set(schema) == {"started_at", *STRIDE_VALUE_FIELDS, *STRIDE_META_FIELDS}
    assert [c for c in VALUE_COLUMNS if c in STRIDE_VALUE_FIELDS] == list(STRIDE_VALUE_FIELDS)
    assert set(VALUE_COLUMNS) <= set(CSV_COLUMNS) and {"activity", "fallback"} <= set(CSV_COLUMNS)


def test_the_test_factory_fills_every_column_of_the_record() -> None:
    (row,) = stride_rows("s", "p", datetime(2026, 11, 1, tzinfo=UTC), "left", 1, fallback=True, activity="running")
    assert {*STRIDE_VALUE_FIELDS, *STRIDE_META_FIELDS} <= set(row)
    assert (row["activity"], row["fallback"]) == ("running", True)
