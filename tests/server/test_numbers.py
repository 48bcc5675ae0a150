"""server.numbers.json_safe: what the JSON columns and responses can hold."""

from __future__ import annotations

import json
import math

import numpy as np

from server.numbers import json_safe


def test_numpy_scalars_and_non_finite_floats_become_json() -> None:
    """A session's summary once failed to store (the job failed) on a numpy bool in a leg's diagnostics."""
    value = {"ok": np.bool_(True), "n": np.int64(3), "x": np.float64(1.5), "nan": math.nan,
             "inf": np.float64(np.inf), "nested": [np.bool_(False), (np.float32(2.0),)]}
    out = json_safe(value)
    assert json.loads(json.dumps(out)) == {"ok": True, "n": 3, "x": 1.5, "nan": None, "inf": None,
                                           "nested": [False, [2.0]]}
    assert type(out["ok"]) is bool  # type: ignore[index]
