"""Batch upload: idempotency (201/200/409), any order, validation with nothing stored, gzip and size limits."""

from __future__ import annotations

import asyncio
import gzip
import json
import time
import zlib
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import numpy as np
import pytest
from fastapi import APIRouter, Depends
from sqlalchemy import event, func, select, text, update

from server.body_limit import INLINE_INFLATE_MAX_BYTES, BodyLimitMiddleware, _GzipInflater, _Reject
from server.config import Settings
from server.errors import ProblemError
from server.sessions import ingest
from server.sessions.models import Batch, Session
from server.sessions.rawdata import load_streams
from server.sessions.routes import UploadRoute, upload_batch
from server.sessions.schemas import BatchIn
from tests.server.helpers import Api, batch_body, bearer, count_rows, open_api


@pytest.fixture
def api(settings: Settings) -> Iterator[Api]:
    small = settings.model_copy(update={"max_body_bytes": 300_000, "max_samples_per_batch": 1000})
    with open_api(small) as a:
        yield a


def _batches(api: Api) -> int:
    with api.engine.connect() as conn:
        return conn.execute(select(func.count()).select_from(Batch)).scalar_one()


def test_new_replay_and_conflict(api: Api) -> None:
    _, dev, sess = api.setup_device_session()
    body = batch_body("L-shank", 3, n=40)
    r = api.upload(dev, sess["id"], body)
    assert r.status_code == 201
    assert r.json() == {"sensor_id": "L-shank", "seq": 3, "samples": 40, "duplicate": False}
    # Identical values in another JSON form (explicit timestamps equal to the implicit ones, gzip): a replay.
    replay = dict(body, timestamps_ms=(body["t0_ms"] + np.arange(40) * 10.0).tolist())
    r = api.upload(dev, sess["id"], replay, gzipped=True)
    assert r.status_code == 200 and r.json()["duplicate"] is True and r.json()["samples"] == 40
    changed = json.loads(json.dumps(body))
    changed["gyro"][5][1] += 0.001
    r = api.upload(dev, sess["id"], changed)
    assert r.status_code == 409
    assert r.headers["content-type"].startswith("application/problem+json")
    assert _batches(api) == 1
    # Same seq on another sensor is a different batch.
    assert api.upload(dev, sess["id"], batch_body("L-thigh", 3, n=40)).status_code == 201
    assert _batches(api) == 2


def test_shuffled_order_with_duplicates_stores_each_sample_once(api: Api) -> None:
    _, dev, sess = api.setup_device_session()
    rng = np.random.default_rng(7)
    n, n_batches = 37, 12
    plan = [(s, q) for s in ("L-thigh", "L-shank") for q in range(n_batches)]
    plan += [plan[i] for i in rng.choice(len(plan), 10)]  # resent after "timeouts"
    rng.shuffle(plan)
    codes = [api.upload(dev, sess["id"], batch_body(s, q, n=n)).status_code for s, q in plan]
    assert codes.count(201) == 2 * n_batches and codes.count(200) == 10
    got = api.client.get(f"/v1/sessions/{sess['id']}", headers=bearer(dev)).json()
    for sensor in ("L-thigh", "L-shank"):
        rec = got["received"][sensor]
        assert (rec["batches"], rec["samples"], rec["gaps"], rec["missing_seq"]) == (n_batches, n * n_batches, 0, [])
        assert rec["first_t_s"] == 0.0 and rec["last_t_s"] == pytest.approx((n * n_batches - 1) / 100.0)
        assert rec["observed_rate_hz"] == pytest.approx(100.0)
    with api.client.app.state.sessionmaker() as db:  # type: ignore[attr-defined]
        streams = {s.sensor_id: s for s in load_streams(db, sess["id"])}
    shank = streams["L-shank"]
    assert shank.t_s.shape == (n * n_batches,)
    np.testing.assert_allclose(np.diff(shank.t_s), 0.01, atol=1e-9)
    expected = np.concatenate([batch_body("L-shank", q, n=n)["gyro"] for q in range(n_batches)])
    np.testing.assert_allclose(shank.gyr, expected, rtol=1e-6)


def test_gaps_from_missing_seq_and_time_jumps(api: Api) -> None:
    _, dev, sess = api.setup_device_session()
    for q in (0, 1, 3):  # seq 2 lost
        assert api.upload(dev, sess["id"], batch_body("L-thigh", q, n=20)).status_code == 201
    # A jump of 5 periods inside one batch of the other sensor.
    t = (np.arange(20) * 10.0)
    t[10:] += 40.0
    body = batch_body("L-shank", 0, n=20)
    body["timestamps_ms"] = t.tolist()
    assert api.upload(dev, sess["id"], body).status_code == 201
    rec = api.client.get(f"/v1/sessions/{sess['id']}", headers=bearer(dev)).json()["received"]
    assert rec["L-thigh"]["gaps"] == 1 and rec["L-thigh"]["missing_seq"] == [2]
    assert rec["L-thigh"]["gap_s"] == pytest.approx(0.2)
    assert rec["L-shank"]["gaps"] == 1 and rec["L-shank"]["gap_s"] == pytest.approx(0.04)


def _nan_body() -> bytes:
    body = json.dumps(batch_body("L-shank", 0, n=5))
    return body.replace(body[body.index("[[") + 2:body.index(",", body.index("[["))], "NaN", 1).encode()


INVALID = {
    "nan literal": lambda: _nan_body(),
    "infinity literal": lambda: _nan_body().replace(b"NaN", b"Infinity"),
    "overflow to inf": lambda: _nan_body().replace(b"NaN", b"1e999"),
    "length mismatch": lambda: json.dumps(dict(batch_body("L-shank", 0, n=5),
                                               acc=batch_body("L-shank", 0, n=4)["acc"])).encode(),
    "row of 2": lambda: json.dumps(dict(batch_body("L-shank", 0, n=5), gyro=[[1, 2]] * 5)).encode(),
    "timestamps count": lambda: json.dumps(dict(batch_body("L-shank", 0, n=5), timestamps_ms=[0, 10])).encode(),
    "timestamps not increasing": lambda: json.dumps(dict(batch_body("L-shank", 0, n=5),
                                                         timestamps_ms=[0, 10, 10, 20, 30])).encode(),
    "t0 far from first timestamp": lambda: json.dumps(dict(batch_body("L-shank", 0, n=3, t0_ms=500.0),
                                                           timestamps_ms=[0, 10, 20])).encode(),
    "negative seq": lambda: json.dumps(batch_body("L-shank", -1, n=5)).encode(),
    "unknown sensor": lambda: json.dumps(batch_body("R-shank", 0, n=5)).encode(),
    "too many samples": lambda: json.dumps(batch_body("L-shank", 0, n=1001)).encode(),
    "empty batch": lambda: json.dumps(dict(batch_body("L-shank", 0, n=5), gyro=[], acc=[])).encode(),
    "not json": lambda: b"{not json",
}


@pytest.mark.parametrize("case", sorted(INVALID))
def test_invalid_batches_get_422_problem_and_change_nothing(api: Api, case: str) -> None:
    _, dev, sess = api.setup_device_session()
    before = count_rows(api.engine)
    headers = {**bearer(dev), "Content-Type": "application/json"}
    r = api.client.post(f"/v1/sessions/{sess['id']}/batches", content=INVALID[case](), headers=headers)
    assert r.status_code == 422, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    problem = r.json()
    assert {"type", "title", "status", "detail"} <= set(problem) and problem["status"] == 422
    assert problem["errors"] and all({"field", "message"} <= set(e) for e in problem["errors"])
    assert count_rows(api.engine) == before
    after = api.client.get(f"/v1/sessions/{sess['id']}", headers=bearer(dev)).json()
    assert after["status"] == "receiving" and after["received"] == sess["received"]


def test_many_invalid_rows_give_a_bounded_error_list(api: Api) -> None:
    _, dev, sess = api.setup_device_session()
    body = json.dumps(dict(batch_body("L-shank", 0, n=500), gyro=[[1.0, 2.0]] * 500))
    r = api.client.post(f"/v1/sessions/{sess['id']}/batches", content=body,
                        headers={**bearer(dev), "Content-Type": "application/json"})
    assert r.status_code == 422
    assert 1 < len(r.json()["errors"]) <= 51
    assert r.json()["errors"][0]["field"].startswith("gyro[0]")


def test_gzip_upload_and_corrupt_gzip(api: Api) -> None:
    _, dev, sess = api.setup_device_session()
    r = api.upload(dev, sess["id"], batch_body("L-thigh", 0, n=200), gzipped=True)
    assert r.status_code == 201 and r.json()["samples"] == 200
    headers = {**bearer(dev), "Content-Encoding": "gzip", "Content-Type": "application/json"}
    for corrupt in (b"this is not gzip", gzip.compress(b'{"sensor_id": "L-thigh"}')[:-6]):
        r = api.client.post(f"/v1/sessions/{sess['id']}/batches", content=corrupt, headers=headers)
        assert r.status_code == 400
        assert r.headers["content-type"].startswith("application/problem+json")
    r = api.client.post(f"/v1/sessions/{sess['id']}/batches", content=b"{}",
                        headers={**bearer(dev), "Content-Encoding": "br"})
    assert r.status_code == 415
    assert _batches(api) == 1


def _bomb(inflated_bytes: int) -> bytes:
    comp = zlib.compressobj(9, zlib.DEFLATED, 16 + zlib.MAX_WBITS)
    block = b"0" * (1 << 20)
    parts = [comp.compress(block) for _ in range(inflated_bytes // len(block))]
    return b"".join(parts) + comp.flush()


def test_gzip_body_past_the_inline_inflate_budget_is_inflated_in_full() -> None:
    seen: list[bytes] = []

    async def app(scope, receive, send) -> None:  # noqa: ANN001
        seen.append((await receive())["body"])

    body = json.dumps({"a": list(range(100_000))}).encode()
    gz = gzip.compress(body)
    assert len(gz) < INLINE_INFLATE_MAX_BYTES < len(body) < 1_000_000
    middleware = BodyLimitMiddleware(app, max_body_bytes=1_000_000)
    scope = {"type": "http", "method": "POST", "path": "/v1/sessions/s1/batches", "headers": [
        (b"content-type", b"application/json"), (b"content-encoding", b"gzip"),
        (b"content-length", str(len(gz)).encode())]}

    async def receive() -> dict:
        return {"type": "http.request", "body": gz, "more_body": False}

    async def send(message: dict) -> None:
        raise AssertionError(f"no answer expected from the middleware: {message}")

    asyncio.run(middleware(scope, receive, send))
    assert seen == [body]


def test_gzip_bomb_gets_413_without_inflating(api: Api) -> None:
    _, dev, sess = api.setup_device_session()
    bomb = _bomb(64 << 20)
    assert len(bomb) < api.settings.max_body_bytes  # small on the wire, 64 MiB inflated
    headers = {**bearer(dev), "Content-Encoding": "gzip", "Content-Type": "application/json"}
    r = api.client.post(f"/v1/sessions/{sess['id']}/batches", content=bomb, headers=headers)
    assert r.status_code == 413
    assert r.headers["content-type"].startswith("application/problem+json")
    assert _batches(api) == 0
    # The inflater stops one byte past the limit: the 64 MiB never exist in memory.
    inflater = _GzipInflater(limit=100_000)
    with pytest.raises(_Reject) as exc:
        for i in range(0, len(bomb), 4096):
            inflater.feed(bomb[i:i + 4096])
    assert exc.value.status == 413 and len(inflater.out) == 100_001


def test_plain_body_over_limit_gets_413(api: Api) -> None:
    _, dev, sess = api.setup_device_session()
    big = json.dumps(batch_body("L-thigh", 0, n=8000)).encode()
    assert len(big) > api.settings.max_body_bytes
    r = api.client.post(f"/v1/sessions/{sess['id']}/batches", content=big,
                        headers={**bearer(dev), "Content-Type": "application/json"})
    assert r.status_code == 413 and r.json()["status"] == 413
    # Chunked, without Content-Length: the streaming count catches it.
    chunks = iter([big[i:i + 65536] for i in range(0, len(big), 65536)])
    r = api.client.post(f"/v1/sessions/{sess['id']}/batches", content=chunks,
                        headers={**bearer(dev), "Content-Type": "application/json"})
    assert r.status_code == 413
    assert _batches(api) == 0


def test_concatenated_gzip_members_are_one_body() -> None:
    data = json.dumps({"a": list(range(1000))}).encode()
    stream = gzip.compress(data[:500]) + gzip.compress(data[500:])
    inflater = _GzipInflater(limit=10**6)
    for i in range(0, len(stream), 7):
        inflater.feed(stream[i:i + 7])
    assert inflater.finish() == data


def test_upload_after_complete_is_409_and_complete_is_idempotent(api: Api) -> None:
    _, dev, sess = api.setup_device_session()
    r = api.client.post(f"/v1/sessions/{sess['id']}/complete", headers=bearer(dev))
    assert r.status_code == 422 and r.json()["type"].endswith("session-empty")
    assert api.upload(dev, sess["id"], batch_body("L-thigh", 0)).status_code == 201
    r = api.client.post(f"/v1/sessions/{sess['id']}/complete", headers=bearer(dev))
    assert r.status_code == 202 and r.json()["status"] == "queued" and r.json()["completed_at"]
    r2 = api.client.post(f"/v1/sessions/{sess['id']}/complete", headers=bearer(dev))
    assert r2.status_code == 202 and r2.json()["status"] == "queued"
    assert r2.json()["completed_at"] == r.json()["completed_at"]
    r = api.upload(dev, sess["id"], batch_body("L-thigh", 1))
    assert r.status_code == 409 and r.headers["content-type"].startswith("application/problem+json")
    # A retry of a stored batch is still acknowledged (its first answer may have been lost); other content is not.
    r = api.upload(dev, sess["id"], batch_body("L-thigh", 0))
    assert r.status_code == 200 and r.json()["duplicate"] is True
    assert api.upload(dev, sess["id"], batch_body("L-thigh", 0, seed=9)).status_code == 409
    assert _batches(api) == 1


@contextmanager
def _statements(api: Api) -> Iterator[list[str]]:
    seen: list[str] = []

    def record(_conn, _cursor, statement, _params, _context, _many) -> None:  # noqa: ANN001
        seen.append(" ".join(statement.split()).upper())

    # On PostgreSQL the upload's INSERT runs on the driver through the group committer
    # (server.sessions.group_commit), on an engine of its own (server.db.make_upload_engine).
    engines = [e for e in (api.engine, api.client.app.state.upload_engine) if e is not None]
    committer = getattr(api.client.app.state, "group_committer", None)
    for engine in engines:
        event.listen(engine, "before_cursor_execute", record)
    if committer is not None:
        insert = committer.insert

        def recorded(sql: str, params: dict) -> bool:
            record(None, None, sql, params, None, False)
            return insert(sql, params)

        committer.insert = recorded
    try:
        yield seen
    finally:
        for engine in engines:
            event.remove(engine, "before_cursor_execute", record)
        if committer is not None:
            del committer.insert


def test_new_batch_is_one_statement_and_replay_checks_only_after_the_insert(api: Api) -> None:
    """A new batch from a known token costs one INSERT (status, access, revocation and the key checked by it);
    the stored batch is read back only when that INSERT stored nothing."""
    _, dev, sess = api.setup_device_session()
    assert api.upload(dev, sess["id"], batch_body("L-thigh", 0, n=10)).status_code == 201  # warms the caches
    with _statements(api) as seen:
        r = api.upload(dev, sess["id"], batch_body("L-thigh", 1, n=10))
    assert r.status_code == 201, r.text
    queries = [q for q in seen if not q.startswith(("SELECT 1", "BEGIN", "COMMIT", "ROLLBACK"))]
    assert len(queries) == 1 and queries[0].startswith("INSERT INTO BATCHES"), seen
    with _statements(api) as seen:
        r = api.upload(dev, sess["id"], batch_body("L-thigh", 1, n=10))
    assert r.status_code == 200 and r.json()["duplicate"] is True
    assert seen.index(next(q for q in seen if q.startswith("INSERT INTO BATCHES"))) < seen.index(
        next(q for q in seen if q.startswith("SELECT BATCHES.CONTENT_SHA256")))
    assert api.upload(dev, sess["id"], batch_body("L-thigh", 1, n=10, seed=3)).status_code == 409
    assert _batches(api) == 2


def test_revoked_token_is_refused_at_once_even_with_its_identity_cached(api: Api) -> None:
    """The token's identity is remembered per process, its revocation is not: the next upload is 401, a replay
    of a stored batch too, and nothing is stored."""
    clin, dev, sess = api.setup_device_session()
    assert api.upload(dev, sess["id"], batch_body("L-thigh", 0)).status_code == 201
    me = api.client.get("/v1/me", headers=bearer(dev)).json()
    r = api.client.delete(f"/v1/tokens/{me['token_id']}", headers=bearer(clin))
    assert r.status_code == 204, r.text
    for seq in (1, 0):
        r = api.upload(dev, sess["id"], batch_body("L-thigh", seq))
        assert r.status_code == 401 and r.headers["content-type"].startswith("application/problem+json")
    assert _batches(api) == 1


def test_upload_without_a_valid_token_is_401_problem_and_stores_nothing(api: Api) -> None:
    """The upload route authenticates by hand (UploadRoute): the same 401 as every other route."""
    _, dev, sess = api.setup_device_session()
    body = json.dumps(batch_body("L-thigh", 0)).encode()
    for headers in ({}, {"Authorization": "Basic abc"}, {"Authorization": "Bearer "},
                    bearer("gm_not-a-real-token")):
        r = api.client.post(f"/v1/sessions/{sess['id']}/batches", content=body,
                            headers={**headers, "Content-Type": "application/json"})
        assert r.status_code == 401, headers
        assert r.headers["content-type"].startswith("application/problem+json")
        assert r.headers["www-authenticate"].startswith("Bearer")
    assert _batches(api) == 0
    assert api.upload(dev, sess["id"], batch_body("L-thigh", 0)).status_code == 201


def test_upload_route_refuses_a_dependency_it_would_not_run() -> None:
    """A dependency declared on the upload route would be documented but never called: refused at start-up."""
    router = APIRouter()
    with pytest.raises(TypeError, match="UploadRoute calls"):
        router.add_api_route("/x/{session_id}", upload_batch, methods=["POST"], route_class_override=UploadRoute,
                             dependencies=[Depends(lambda: None)])


def test_other_patients_device_cannot_upload_into_a_session(api: Api) -> None:
    """Access is part of the INSERT: another patient's device gets 404 and stores nothing."""
    clin, dev, sess = api.setup_device_session()
    other = api.patient(clin, display_name="other")
    tok = api.client.post(f"/v1/patients/{other['id']}/device-tokens", headers=bearer(clin)).json()["token"]
    assert api.upload(tok, sess["id"], batch_body("L-thigh", 0)).status_code == 404
    assert api.upload(dev, sess["id"], batch_body("L-thigh", 0)).status_code == 201
    assert api.upload(tok, sess["id"], batch_body("L-thigh", 1)).status_code == 404
    assert _batches(api) == 1


def test_batch_racing_complete_is_refused_not_stored(api: Api) -> None:
    """A batch whose status check saw "receiving" just before /complete committed must not be stored."""
    _, dev, sess = api.setup_device_session()
    assert api.upload(dev, sess["id"], batch_body("L-thigh", 0)).status_code == 201
    sm = api.client.app.state.sessionmaker  # type: ignore[attr-defined]
    with sm() as db:
        stale = db.get(Session, sess["id"])
        assert stale is not None and stale.status == "receiving"
        _ = stale.sensors
        db.expunge(stale)  # keeps its loaded, soon stale, state
        db.rollback()
        assert api.client.post(f"/v1/sessions/{sess['id']}/complete", headers=bearer(dev)).status_code == 202
        with pytest.raises(ProblemError) as exc:
            ingest.ingest_batch(db, stale, BatchIn(**batch_body("L-thigh", 1)), max_samples=1000)
    assert exc.value.status == 409
    assert _batches(api) == 1


def test_upload_waiting_for_a_completing_session_is_refused_not_stored(api: Api) -> None:
    """An upload arriving while /complete holds the session (row lock on PostgreSQL, write lock on SQLite) waits,
    then sees the new status: 409, and the completed session gains no sample."""
    _, dev, sess = api.setup_device_session()
    assert api.upload(dev, sess["id"], batch_body("L-thigh", 0)).status_code == 201
    sm = api.client.app.state.sessionmaker  # type: ignore[attr-defined]
    with sm() as db, ThreadPoolExecutor(1) as pool:
        assert ingest.still_in_status(db, sess["id"], ("receiving",))
        pending = pool.submit(api.upload, dev, sess["id"], batch_body("L-thigh", 1))
        time.sleep(0.5)
        assert not pending.done()
        db.execute(update(Session).where(Session.id == sess["id"]).values(status="queued"))
        db.commit()
        r = pending.result(timeout=30)
    assert r.status_code == 409 and r.json()["type"].endswith("session-not-receiving")
    assert _batches(api) == 1


def test_uploads_racing_complete_never_add_a_batch_after_it(api: Api) -> None:
    """Four sensors' uploads in flight while /complete runs: once its 202 is back, the stored batches never change,
    and every stored batch was acknowledged 201 (none refused yet stored)."""
    clin, _, _ = api.setup_device_session()
    patient = api.patient(clin)
    dev = api.device(clin, patient["id"])
    sensors = [{"sensor_id": f"S{i}", "leg": leg, "segment": seg, "sample_rate_hz": 100.0}
               for i, (leg, seg) in enumerate([("left", "thigh"), ("left", "shank"), ("right", "thigh"),
                                                ("right", "shank")])]
    sid = api.session(dev, patient["id"], sensors=sensors)["id"]
    for s in sensors:  # warms the caches so the race is with the one-statement path
        assert api.upload(dev, sid, batch_body(s["sensor_id"], 0, n=20)).status_code == 201
    acked: dict[str, set[int]] = {s["sensor_id"]: {0} for s in sensors}

    def sender(sensor_id: str) -> None:
        for seq in range(1, 40):
            code = api.upload(dev, sid, batch_body(sensor_id, seq, n=20)).status_code
            assert code in (201, 409)
            if code == 201:
                acked[sensor_id].add(seq)
            else:
                return

    with ThreadPoolExecutor(5) as pool:
        senders = [pool.submit(sender, s["sensor_id"]) for s in sensors]
        time.sleep(0.2)
        r = api.client.post(f"/v1/sessions/{sid}/complete", headers=bearer(dev))
        assert r.status_code == 202
        at_complete = _batches(api)
        for f in senders:
            f.result(timeout=60)
    assert _batches(api) == at_complete
    with api.engine.connect() as conn:
        stored = conn.execute(select(Batch.sensor_id, Batch.seq).where(Batch.session_id == sid)).all()
    assert {(a, b) for a, b in stored} == {(k, q) for k, seqs in acked.items() for q in seqs}
    assert sum(r.json()["received"][k]["batches"] for k in acked) == at_complete


def test_concurrent_replays_store_once(api: Api) -> None:
    """Eight simultaneous sends of one batch (and of a session create): one is stored, the others are replays."""
    _, dev, sess = api.setup_device_session()
    body = batch_body("L-shank", 5, n=200)
    with ThreadPoolExecutor(8) as pool:
        codes = sorted(pool.map(lambda _: api.upload(dev, sess["id"], body).status_code, range(8)))
    assert codes == [200] * 7 + [201]
    assert _batches(api) == 1
    me = api.client.get("/v1/me", headers=bearer(dev)).json()
    with ThreadPoolExecutor(6) as pool:
        ids = list(pool.map(lambda _: api.session(dev, me["patient_id"], client_session_id="same")["id"], range(6)))
    assert len(set(ids)) == 1


def test_bunched_timestamps_are_refused(api: Api) -> None:
    """Stamps far denser than the declared rate (here 1 us apart in pairs) are a client bug: 422, nothing stored."""
    _, dev, sess = api.setup_device_session()
    body = batch_body("L-shank", 0, n=20)
    body["timestamps_ms"] = [10.0 * (i // 2) + 0.001 * (i % 2) for i in range(20)]
    r = api.upload(dev, sess["id"], body)
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "timestamps_ms"
    assert "np.float64" not in r.text
    assert _batches(api) == 0


def test_overlapping_batches_under_new_seq_count_once_in_processing(api: Api) -> None:
    """The same samples re-sent under other seq numbers with stamps 1 us later are merged, not doubled."""
    _, dev, sess = api.setup_device_session()
    for seq in range(4):
        body = batch_body("L-shank", seq, n=50, timestamps=True)
        assert api.upload(dev, sess["id"], body).status_code == 201
        shifted = dict(body, seq=100 + seq, t0_ms=body["t0_ms"] + 0.001,
                       timestamps_ms=[t + 0.001 for t in body["timestamps_ms"]])
        assert api.upload(dev, sess["id"], shifted).status_code == 201
    with api.client.app.state.sessionmaker() as db:  # type: ignore[attr-defined]
        (stream,) = load_streams(db, sess["id"])
    assert stream.t_s.size == 200
    assert np.all(np.diff(stream.t_s) > 0.009)


def test_malformed_json_names_the_body(api: Api) -> None:
    clin, _ = api.clinician()
    r = api.client.post("/v1/patients", content=b'{"display_name": ', headers={**bearer(clin),
                                                                            "Content-Type": "application/json"})
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "body"


@pytest.mark.parametrize(("jump_periods", "gaps"), [(1.6, 0), (1.9, 1)])
def test_time_jumps_count_as_gaps_by_the_pipelines_rule(api: Api, jump_periods: float, gaps: int) -> None:
    """received.gaps uses the pipeline's gap threshold (PrepareParams.gap_factor sample periods), so it agrees with the
    processing summary's gaps: a step of 1.6 periods is no gap to either, 1.9 periods is one to both."""
    from pipeline.params import WALKING

    assert 1.6 < WALKING.prepare.gap_factor < 1.9
    _, dev, sess = api.setup_device_session()
    t = np.arange(20) * 10.0
    t[10:] += (jump_periods - 1.0) * 10.0
    body = batch_body("L-shank", 0, n=20)
    body["timestamps_ms"] = t.tolist()
    assert api.upload(dev, sess["id"], body).status_code == 201
    rec = api.client.get(f"/v1/sessions/{sess['id']}", headers=bearer(dev)).json()["received"]
    assert rec["L-shank"]["gaps"] == gaps


def test_uploads_run_on_threads_of_their_own_within_the_pool(settings: Settings) -> None:
    s = settings.model_copy(update={"db_pool_size": 20, "db_max_overflow": 10, "upload_threads": 8})
    # The upload threads and the other routes' threads together never outnumber the pooled connections.
    assert (s.upload_thread_count, s.api_threads) == (8, 22)
    tight = settings.model_copy(update={"db_pool_size": 3, "db_max_overflow": 0, "upload_threads": 8})
    assert tight.upload_thread_count == 1
    with open_api(s) as api:
        _, dev, sess = api.setup_device_session()
        assert api.upload(dev, sess["id"], batch_body("L-shank", 0, n=40)).status_code == 201
        pool = api.client.app.state.upload_pool
        assert pool._max_workers == 8 and len(pool._threads) == 1  # one upload so far: one thread started


def test_an_upload_on_a_dead_pooled_connection_is_stored_once_on_a_new_one(postgres_url: str, tmp_path,  # noqa: ANN001
                                                                          caplog: pytest.LogCaptureFixture) -> None:
    # The upload engine has no pre-ping: a connection PostgreSQL dropped (restart, idle timeout) is found dead by
    # the INSERT itself, which then runs once more; the batch is stored once and answered 201.
    from tests.conftest import _truncate_all

    _truncate_all(postgres_url)
    s = Settings(database_url=postgres_url, data_dir=tmp_path / "data", job_runner="manual")
    with open_api(s) as api:
        _, dev, sess = api.setup_device_session()
        assert api.upload(dev, sess["id"], batch_body("L-shank", 0, n=40)).status_code == 201
        upload_engine = api.client.app.state.upload_engine
        assert upload_engine.pool.checkedin() >= 1
        with api.engine.connect() as conn:
            killed = conn.execute(text("SELECT count(pg_terminate_backend(pid)) FROM pg_stat_activity WHERE "
                                       "datname = current_database() AND pid <> pg_backend_pid() AND state = 'idle'"
                                       )).scalar_one()
            conn.commit()
        assert killed >= 1
        r = api.upload(dev, sess["id"], batch_body("L-shank", 1, n=40))
        assert r.status_code == 201, r.text
        assert "pooled connection was dead" in caplog.text
        assert api.upload(dev, sess["id"], batch_body("L-shank", 1, n=40)).status_code == 200
        assert _batches(api) == 2


def test_a_body_that_never_finishes_is_408_within_the_body_timeout() -> None:
    """Headers promise 100 bytes, 4 arrive, then nothing: the request's slot is given back after the timeout."""
    called: list[bool] = []
    sent: list[dict] = []

    async def app(scope, receive, send) -> None:  # noqa: ANN001
        called.append(True)

    middleware = BodyLimitMiddleware(app, max_body_bytes=1_000_000, body_timeout_s=0.3)
    scope = {"type": "http", "method": "POST", "path": "/v1/sessions/s1/batches", "headers": [
        (b"content-type", b"application/json"), (b"content-length", b"100")]}
    chunks = iter([{"type": "http.request", "body": b'{"se', "more_body": True}])

    async def receive() -> dict:
        try:
            return next(chunks)
        except StopIteration:
            await asyncio.sleep(3600)  # the client keeps the socket open and sends nothing
            raise AssertionError("unreachable") from None

    async def send(message: dict) -> None:
        sent.append(message)

    t0 = time.perf_counter()
    asyncio.run(middleware(scope, receive, send))
    assert time.perf_counter() - t0 < 2.0
    assert not called
    assert sent[0]["status"] == 408
    assert (b"connection", b"close") in sent[0]["headers"]
    assert json.loads(sent[1]["body"])["status"] == 408
