"""Sentences of the clinician pages built from the API's attention flags."""

from __future__ import annotations

from zoneinfo import ZoneInfo

from pipeline.reasons import REASONS
from server.results.schemas import StrideOut
from server.ui import words


def test_a_silent_patient_is_counted_in_whole_days() -> None:
    tz = ZoneInfo("Europe/Berlin")
    flag = {"kind": "silent", "days_without_data": 9.5, "last_session_at": "2026-11-21T23:30:00+00:00"}
    # 9.5 days is nine whole days (rounding would say ten); the date is the patient's local one (Sun 22 Nov).
    assert words.flag(flag, tz) == "No session for 9 days (last on Sun 22 Nov 2026)."
    assert words.flag({**flag, "days_without_data": 10.0}, tz).startswith("No session for 10 days")


def test_every_code_has_words_on_the_pages_and_a_line_in_the_api_schema() -> None:
    assert words.REASONS.keys() == REASONS.keys()
    described = StrideOut.model_json_schema()["properties"]["quality_reasons"]["description"]
    assert all(f"`{code}`" in described for code in REASONS)
