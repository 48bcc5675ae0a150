"""A short run of bench.load against a real uvicorn server: phones uploading at once lose and double nothing
and never see a server error; with kill -9 of the API mid-run the retried batches are still all stored once."""

from __future__ import annotations

import pytest

from bench.load import parse_args, run


@pytest.mark.parametrize("kill", [False, True], ids=["steady", "kill-9"])
def test_twenty_phones_lose_and_double_nothing_and_see_no_5xx(kill: bool) -> None:
    extra = ["--kill"] if kill else []
    out = run(parse_args(["--phones", "20", "--seconds", "5", "--drain-s", "40", *extra]))
    assert out["sent"] >= 20 * 2 * 4
    assert out["five_xx_not_503"] == 0, out["statuses"]
    assert out["lost_batches"] == 0
    assert out["doubled_batches"] == 0
    assert out["retry_after_missing"] == 0
    # every batch sent was acknowledged within the drain time, so none is left for the app to hold
    assert out["unfinished"] == 0
    assert out["acked"] == out["sent"]
    assert out["stored_batches"] == out["acked"]
