"""Each patient's attention row (flags and exposure precomputed when a session is processed) stays what a fresh
computation gives: after a session is processed, reprocessed (failing, then succeeding), while one is pending, after
a rule change (backfill) and when the patient is deleted."""

from __future__ import annotations

import json
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from sqlalchemy import select, update
from sqlalchemy.orm import Session as DbSession

from pipeline.simulate import SimConfig, simulate_session
from server.auth.models import Clinician
from server.db import make_engine, make_sessionmaker, new_id
from server.enums import SessionStatus
from server.patients.models import Patient
from server.patients.service import delete_patient
from server.processing.jobs import run_queued
from server.sessions.models import Session
from server.trends.attention import attention_list
from server.trends.attention.evidence import RULES_VERSION, patients_needing_evidence
from server.trends.attention.service import evidence_document
from server.trends.models import AttentionEvidence
from server.trends.summaries import backfill
from server.utc import as_utc, utcnow
from tests.support.seed import add_session, add_stream_batches

NOW = datetime.now(UTC).replace(microsecond=0)
DAYS = [27, 24, 21, 12, 8, 1]
PEAKS = [60, 61, 59, 45, 46, 44]  # a clear decline


@pytest.fixture
def factory(database_url: str) -> Iterator:
    engine = make_engine(database_url)
    yield make_sessionmaker(engine)
    engine.dispose()


def _declining_patient(db: DbSession) -> tuple[str, str, list[str]]:
    c = Clinician(name="Dr. State")
    db.add(c)
    db.flush()
    p = Patient(clinician_id=c.id, timezone="UTC", affected_leg="left", display_name="S",
                created_at=NOW - timedelta(days=60))
    db.add(p)
    db.flush()
    sids = [add_session(db, p.id, NOW - timedelta(days=d), {"left": {
        "n": 30, "peak_swing_flexion_deg": np.where(np.arange(30) % 2 == 0, v - 1.0, v + 1.0)}})
        for d, v in zip(DAYS, PEAKS, strict=True)]
    return c.id, p.id, sids


def _row(db: DbSession, pid: str) -> AttentionEvidence | None:
    db.expire_all()
    return db.get(AttentionEvidence, pid)


def _assert_fresh(db: DbSession, pid: str) -> AttentionEvidence:
    """The stored row equals what a recomputation from the summaries gives now."""
    row = _row(db, pid)
    assert row is not None
    as_of, doc = evidence_document(db, pid)
    assert as_utc(row.as_of) == as_of
    assert json.loads(row.flags) == json.loads(json.dumps(doc["presets"]))
    processed = db.execute(select(Session.started_at).where(
        Session.patient_id == pid, Session.status.in_([SessionStatus.done, SessionStatus.failed]))).scalars().all()
    assert row.n_sessions == len(processed)
    assert as_utc(row.first_session_at) == min(as_utc(t) for t in processed)
    assert row.rules_version == RULES_VERSION
    return row


def _flags(db: DbSession, clin: str, pid: str) -> tuple[list[dict], dict]:
    out = attention_list(db, clinician_id=clin, now=NOW)
    item = next((it for it in out["items"] if it["patient"]["id"] == pid), None)
    return (item["flags"] if item else []), out


def _failing(*_a: object, **_k: object) -> object:
    raise RuntimeError("simulated processing failure")


def test_the_row_follows_processing_and_reprocessing(factory) -> None:
    with factory() as db:
        clin, pid, sids = _declining_patient(db)
        db.commit()
        row = _assert_fresh(db, pid)
        assert row.n_sessions == 6 and as_utc(row.as_of) == NOW - timedelta(days=1)
        flags, _ = _flags(db, clin, pid)
        assert [f["kind"] for f in flags] == ["declining"] and flags[0]["n_sessions"] == 6

        # Reprocess the latest session: while it is queued the row still answers (its last session counts).
        db.execute(update(Session).where(Session.id == sids[-1]).values(status=SessionStatus.queued))
        db.commit()
        flags, out = _flags(db, clin, pid)
        assert [f["kind"] for f in flags] == ["declining"]
        assert next(it for it in out["items"] if it["patient"]["id"] == pid)["last_session_at"] == \
            (NOW - timedelta(days=1)).isoformat()
    # The reprocess fails: its strides are gone, the trend has five sessions left, the failed run still counts
    # as a processed session of the patient.
    assert run_queued(factory, processor=_failing) == 1
    with factory() as db:
        assert db.get(Session, sids[-1]).status == SessionStatus.failed
        row = _assert_fresh(db, pid)
        assert row.n_sessions == 6
        flags, _ = _flags(db, clin, pid)
        assert [f["kind"] for f in flags] == ["declining"] and flags[0]["n_sessions"] == 5

        # A new session through the real pipeline: pending first (the patient is not silent meanwhile) ...
        sim = simulate_session(SimConfig(pattern="normal", seed=3, duration_s=30.0, activities=("standing",),
                                         legs=("left",)))
        started = NOW - timedelta(hours=3)
        new = new_id()
        db.add(Session(id=new, patient_id=pid, client_session_id=new, started_at=started, activity="walking",
                       status=SessionStatus.queued, completed_at=utcnow()))
        db.flush()
        add_stream_batches(db, new, sim.streams, 2)
        db.commit()
        out = attention_list(db, clinician_id=clin, now=NOW + timedelta(days=4))
        item = next(it for it in out["items"] if it["patient"]["id"] == pid)
        assert item["last_session_at"] == started.isoformat()
        assert "silent" in [f["kind"] for f in item["flags"]]  # 4 days after it, with the default 3-day limit
        quiet = next(f for f in item["flags"] if f["kind"] == "silent")
        assert quiet["days_without_data"] == pytest.approx(4.1, abs=0.01)
    # ... then processed: the row moves to it.
    assert run_queued(factory) == 1
    with factory() as db:
        assert db.get(Session, new).status == SessionStatus.done
        row = _assert_fresh(db, pid)
        assert row.n_sessions == 7 and as_utc(row.as_of) == started


def test_a_rule_change_is_backfilled_and_a_deleted_patient_loses_the_row(factory) -> None:
    with factory() as db:
        clin, pid, _ = _declining_patient(db)
        db.commit()
        row = _row(db, pid)
        row.rules_version = "older rules"
        row.flag_index = ""
        row.flags = "{}"
        db.commit()
        assert pid in patients_needing_evidence(db)
        assert _flags(db, clin, pid)[0] == []  # the stale row says nothing until backfilled
    backfill(factory)
    with factory() as db:
        _assert_fresh(db, pid)
        assert pid not in patients_needing_evidence(db)
        assert [f["kind"] for f in _flags(db, clin, pid)[0]] == ["declining"]

        # Deleted by the service the API uses: the row goes with it (ON DELETE CASCADE), the list forgets them.
        delete_patient(db, pid)
        db.commit()
        assert _row(db, pid) is None
        flags, out = _flags(db, clin, pid)
        assert flags == [] and out["n_patients"] == 0
