"""Sessions: create (idempotent per client_session_id), batch upload, complete, status, reprocess."""

from __future__ import annotations

import asyncio
import contextvars
import logging
from collections.abc import Callable, Coroutine
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC
from typing import Any

from fastapi import APIRouter, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute
from pydantic import ValidationError
from sqlalchemy import Engine, Executable, String, bindparam, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session as DbSession
from sqlalchemy.orm import sessionmaker

from server.auth.service import (
    Principal,
    get_patient_for,
    get_session_for,
    require_role,
    session_visible_to,
    session_visible_to_role,
    token_is_live,
    visibility_params,
)
from server.config import Settings
from server.db import storable_key
from server.deps import (
    AppSettings,
    Caller,
    Db,
    UploadCaller,
    app_cache,
    bearer_scheme,
    ended,
    token_identity,
    unauthorized_token,
)
from server.enums import Role, SessionStatus
from server.errors import ProblemError, conflict, invalid
from server.ops import metrics as ops_metrics
from server.processing.queue import enqueue
from server.sessions.bounds import session_span_problem
from server.sessions.group_commit import GroupCommitter, driver_sql
from server.sessions.ingest import (
    IngestOutcome,
    guarded_insert,
    ingest_batch,
    insert_batch,
    insert_params,
    prepare_batch,
    received_summary,
    still_in_status,
)
from server.sessions.models import Batch, Session, SessionSensor
from server.sessions.schemas import BatchIn, BatchOut, SensorOut, SessionIn, SessionOut
from server.ttl_cache import TtlCache
from server.utc import utcnow

log = logging.getLogger("gaitmon.api")
router = APIRouter(prefix="/v1/sessions", tags=["sessions and upload"])


def parse_batch(raw: bytes, max_samples: int) -> BatchIn:
    """The batch body, parsed and validated by pydantic-core straight from the bytes.

    About 3x faster than FastAPI's json.loads + validation for a 20 000-sample batch; NaN/Infinity literals
    parse and are then rejected by the finite-number check.
    """
    # Every sample is a gyro and an acc row, each opening a bracket: counted on the bytes (memchr speed) before
    # pydantic builds a Python list per row, so a 1M-row body costs milliseconds, not a gigabyte.
    brackets = raw.count(b"[")
    if brackets > bracket_limit(max_samples):
        raise invalid("gyro", f"the body holds more than {max_samples} samples, the limit per batch ({brackets} "
                              f"arrays)")
    # and every JSON value but the last of each container is followed by a comma: an array of a million empty
    # objects or bare numbers (a few kB gzip'd) would otherwise cost one validation error object per element
    commas = raw.count(b",")
    if commas > comma_limit(max_samples):
        raise invalid("gyro", f"the body holds more values than {max_samples} samples can ({commas} separators)")
    try:
        return BatchIn.model_validate_json(raw)
    except ValidationError as exc:
        errors = exc.errors(include_url=False, include_context=False, include_input=False)
        raise RequestValidationError([{**e, "loc": ("body", *e["loc"])} for e in errors]) from None


def comma_limit(max_samples: int) -> int:
    """Most ``,`` a valid batch body can hold: per sample three gyro and three acc values and a timestamp, the
    top-level fields, and commas inside the sensor id (at most its length)."""
    return 7 * max_samples + 16 + 64


def bracket_limit(max_samples: int) -> int:
    """Most ``[`` a valid batch body can hold: a gyro and an acc row per sample, the three arrays, the
    timestamps array, and brackets inside the sensor id (at most its length)."""
    return 2 * max_samples + 4 + 64


def session_out(db: DbSession, s: Session) -> SessionOut:
    """The response form of a session with what each sensor received."""
    return SessionOut.model_validate({
        "id": s.id, "patient_id": s.patient_id, "client_session_id": s.client_session_id,
        "started_at": s.started_at, "activity": s.activity, "status": s.status, "error": s.error,
        "sensors": [SensorOut.model_validate(x) for x in s.sensors], "received": received_summary(db, s),
        "summary": s.summary, "algorithm_version": s.algorithm_version, "created_at": s.created_at,
        "completed_at": s.completed_at, "processed_at": s.processed_at, "attempts": s.attempts or 0,
    })


def _sensor_key(sensors: list) -> set[tuple]:
    return {(x.sensor_id, x.leg, x.segment, float(x.sample_rate_hz), x.gyro_unit, x.acc_unit) for x in sensors}


def _existing(db: DbSession, patient_id: str, client_session_id: str) -> Session | None:
    return db.scalar(select(Session).where(Session.patient_id == patient_id,
                                           Session.client_session_id == client_session_id))


def _same_or_conflict(existing: Session, body: SessionIn) -> Session:
    if _sensor_key(existing.sensors) != _sensor_key(body.sensors):
        raise conflict(f"client_session_id {body.client_session_id!r} is already used by a session with "
                       f"different sensors", slug="session-conflict")
    return existing


@router.post("", status_code=201, response_model=SessionOut,
             responses={200: {"description": "The session with this client_session_id already existed",
                              "model": SessionOut},
                        409: {"description": "The client_session_id is used by a session with other sensors"}},
             summary="Start a session (a repeated client_session_id returns the existing one with 200)")
def create_session(body: SessionIn, response: Response, db: Db, caller: Caller) -> SessionOut:
    """Create a session (idempotent on the app's client_session_id)."""
    with ended(db):
        return _create_session(body, response, db, caller)


def _create_session(body: SessionIn, response: Response, db: DbSession, caller: Principal) -> SessionOut:
    patient = get_patient_for(db, caller, body.patient_id)
    existing = _existing(db, patient.id, body.client_session_id)
    if existing is not None:
        response.status_code = 200
        return session_out(db, _same_or_conflict(existing, body))
    # Stored in UTC: SQLite drops the offset of an aware datetime instead of converting it.
    session = Session(patient_id=patient.id, client_session_id=body.client_session_id,
                      started_at=body.started_at.astimezone(UTC), activity=body.activity,
                      status=SessionStatus.receiving)
    session.sensors = [SessionSensor(sensor_id=x.sensor_id, leg=x.leg, segment=x.segment,
                                     sample_rate_hz=x.sample_rate_hz, gyro_unit=x.gyro_unit, acc_unit=x.acc_unit)
                       for x in body.sensors]
    db.add(session)
    try:
        db.commit()
    except IntegrityError:
        # Created concurrently by a retry of the same app: answer as for a repeat.
        db.rollback()
        existing = _existing(db, patient.id, body.client_session_id)
        if existing is None:
            raise
        response.status_code = 200
        return session_out(db, _same_or_conflict(existing, body))
    log.info("session %s created for patient %s (%d sensors)", session.id, patient.id, len(body.sensors))
    return session_out(db, session)


@router.get("/{session_id}", response_model=SessionOut,
            summary="Status, what was received per sensor (batches, samples, gaps) and the result summary")
def get_session(session_id: str, db: Db, caller: Caller) -> SessionOut:
    """A session with what it received and, once processed, its summary."""
    with ended(db):
        return session_out(db, get_session_for(db, caller, session_id))


class UploadRoute(APIRoute):
    """The upload route, called once a second per sensor of every phone: served without FastAPI's generic
    dependency solving and response-model validation, which cost more CPU than the rest of the request.

    Its dependencies are the same functions, called directly in the order FastAPI would (the bearer scheme, then
    :func:`server.deps.token_identity`), and :func:`upload_batch` returns a :class:`BatchOut` that needs no second
    validation. Path, parameters, responses and the OpenAPI document are the ones FastAPI derives from the endpoint.
    """

    # What handle() calls by hand; anything else declared on the route would be documented but never run.
    HANDLED = frozenset({"token_identity", "HTTPBearer", "get_app_settings"})

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        calls: list[Any] = []
        pending = list(self.dependant.dependencies)
        while pending:
            dep = pending.pop()
            calls.append(dep.call)
            pending.extend(dep.dependencies)
        names = {getattr(c, "__name__", type(c).__name__) for c in calls}
        if self.dependencies or names != self.HANDLED:
            raise TypeError(f"UploadRoute calls {sorted(self.HANDLED)} itself; the route declares {sorted(names)}"
                            f" and {len(self.dependencies)} route dependencies")

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        async def handle(request: Request) -> Response:
            caller = await token_identity(request, await bearer_scheme(request))
            response = Response(status_code=201)
            out = await upload_batch(request.path_params["session_id"], request, response, caller,
                                     request.app.state.settings)
            return Response(out.model_dump_json(), status_code=response.status_code, media_type="application/json")

        return handle


async def upload_batch(session_id: str, request: Request, response: Response, caller: UploadCaller,
                       settings: AppSettings) -> BatchOut:
    """Store one batch of one sensor (idempotent on sensor_id and seq)."""
    raw = await request.body()
    rates = app_cache(request, "session_sensor_rates", SENSOR_RATES_TTL_S)
    # Parse, validate and store in one thread hop; the connection is back in the pool before the answer.
    # On an executor of their own: anyio's thread hop (limiter, checkpoints, its worker queue) cost ~0.05 ms more
    # per batch. The context goes along, so the thread's log lines carry the request id.
    outcome = await asyncio.get_running_loop().run_in_executor(
        _upload_pool(request, settings), contextvars.copy_context().run, _upload, request.app.state.sessionmaker,
        _autocommit(request), getattr(request.app.state, "group_committer", None), rates, caller, session_id, raw,
        settings.max_samples_per_batch)
    response.status_code = 201 if outcome.created else 200
    ops_metrics.batch_ingested(outcome.samples, stored=outcome.created)
    log.debug("batch session=%s sensor=%s seq=%d samples=%d -> %s", session_id, outcome.sensor_id, outcome.seq,
              outcome.samples, "stored" if outcome.created else "duplicate")
    return BatchOut(sensor_id=outcome.sensor_id, seq=outcome.seq, samples=outcome.samples,
                    duplicate=not outcome.created)


router.add_api_route(
    "/{session_id}/batches", upload_batch, methods=["POST"], status_code=201, response_model=BatchOut,
    responses={200: {"description": "Identical replay of a stored batch; nothing stored", "model": BatchOut},
               409: {"description": "Same (sensor_id, seq) with different content, or session completed"},
               413: {"description": "Body larger than the limit (after gzip decompression)"}},
    openapi_extra={"requestBody": {"required": True, "content": {
        "application/json": {"schema": BatchIn.model_json_schema()}}}},
    summary="Upload one batch of one sensor (idempotent per sensor_id and seq; gzip accepted)",
    route_class_override=UploadRoute)


# A session's declared sensors never change once it exists; remembered per (token, session) that could see them.
SENSOR_RATES_TTL_S = 300.0


def _visible_sensor_rates(db: DbSession, caller: Principal, session_id: str) -> dict[str, float]:
    if not storable_key(session_id):
        return {}
    rows = db.execute(select(SessionSensor.sensor_id, SessionSensor.sample_rate_hz)
                      .join(Session, Session.id == SessionSensor.session_id)
                      .where(Session.id == session_id, session_visible_to(caller))).all()
    db.rollback()
    return {r.sensor_id: r.sample_rate_hz for r in rows}


def _upload_pool(request: Request, settings: Settings) -> ThreadPoolExecutor:
    # Uploads get threads of their own (Settings.upload_threads): a few, so that parsing in threads never starves
    # the event loop of the GIL, and the other routes keep theirs under a flood of uploads.
    pool = getattr(request.app.state, "upload_pool", None)
    if pool is None:
        pool = request.app.state.upload_pool = ThreadPoolExecutor(settings.upload_thread_count,
                                                                  thread_name_prefix="gaitmon-upload")
    return pool


def _autocommit(request: Request) -> Engine:
    # The guarded insert is one statement: run alone it needs no BEGIN/COMMIT round trips.
    engine = getattr(request.app.state, "upload_engine", None) or getattr(request.app.state, "autocommit_engine",
                                                                           None)
    if engine is None:
        engine = request.app.state.engine.execution_options(isolation_level="AUTOCOMMIT")
        request.app.state.autocommit_engine = engine
    return engine


_UPLOAD_INSERTS: dict[tuple[str, str], Executable] = {}


def _upload_insert(dialect: str, role: str) -> Executable:
    """The upload's guarded insert for a caller role, built once: the token must be live and the session
    visible to the caller, checked by the INSERT itself."""
    stmt = _UPLOAD_INSERTS.get((dialect, role))
    if stmt is None:
        stmt = guarded_insert(dialect, (token_is_live(bindparam("live_token_id", type_=String)),
                                        session_visible_to_role(role)))
        _UPLOAD_INSERTS[(dialect, role)] = stmt
    return stmt


_DRIVER_SQL: dict[str, tuple[str, dict[str, Any]]] = {}


def _upload_driver_sql(engine: Engine, role: str) -> tuple[str, dict[str, Any]]:
    """:func:`_upload_insert` compiled for the driver, once per role (run by :class:`GroupCommitter`)."""
    out = _DRIVER_SQL.get(role)
    if out is None:
        out = _DRIVER_SQL[role] = driver_sql(engine, _upload_insert(engine.dialect.name, role))
    return out


def _upload(sm: sessionmaker[DbSession], autocommit: Engine, committer: GroupCommitter | None,
            rates_cache: TtlCache, caller: Principal, session_id: str, raw: bytes, max_samples: int,
            ) -> IngestOutcome:
    body = parse_batch(raw, max_samples)
    try:
        return _store(sm, autocommit, committer, rates_cache, caller, session_id, body, max_samples)
    except ProblemError as exc:
        log.info("batch session=%s sensor=%s seq=%d rejected %d: %s", session_id, body.sensor_id, body.seq,
                 exc.status, exc.detail)
        raise


def _store(sm: sessionmaker[DbSession], autocommit: Engine, committer: GroupCommitter | None,
           rates_cache: TtlCache, caller: Principal, session_id: str, body: BatchIn, max_samples: int,
           ) -> IngestOutcome:
    """The hot path is one INSERT whose WHERE checks the token, the caller's access and the session's status;
    anything it refuses (replay, completed, revoked, unknown sensor or session) goes through the full checks."""
    key = (caller.token_id, session_id)
    rates = rates_cache.get(key)
    if rates is None:
        with sm() as db:
            rates = _visible_sensor_rates(db, caller, session_id)
        if rates:
            rates_cache.put(key, rates)
    if body.sensor_id in rates:
        prepared = prepare_batch(rates, body, max_samples=max_samples)
        params = {**insert_params(session_id, prepared), **visibility_params(caller), "live_token_id": caller.token_id}
        if committer is not None:  # PostgreSQL
            sql, fixed = _upload_driver_sql(autocommit, caller.role)
            stored = committer.insert(sql, {**fixed, **params})
        else:
            with autocommit.connect() as conn:
                stored = insert_batch(conn, _upload_insert(autocommit.dialect.name, caller.role), params)
        if stored:
            return IngestOutcome(created=True, sensor_id=prepared.sensor_id, seq=prepared.seq,
                                 samples=prepared.n_samples)
    with sm() as db:
        if not db.scalar(select(token_is_live(caller.token_id))):
            raise unauthorized_token()
        session = get_session_for(db, caller, session_id)
        return ingest_batch(db, session, body, max_samples=max_samples)


@router.post("/{session_id}/complete", status_code=202, response_model=SessionOut,
             responses={422: {"description": "The session has no batches: nothing to process"}},
             summary="No more uploads: queue the session for processing (idempotent)")
def complete_session(session_id: str, db: Db, caller: Caller, settings: AppSettings) -> SessionOut:
    """No more data will come: queue the session for processing."""
    with ended(db):
        return _complete_session(session_id, db, caller, settings)


def _complete_session(session_id: str, db: DbSession, caller: Principal, settings: Settings) -> SessionOut:
    session = get_session_for(db, caller, session_id, for_update=True)
    if session.status != SessionStatus.receiving or not still_in_status(db, session.id, (SessionStatus.receiving,)):
        # Already completed (idempotent): 202 with the current state.
        db.rollback()
        return session_out(db, db.get(Session, session_id, populate_existing=True) or session)
    n_batches = db.scalar(select(func.count()).select_from(Batch).where(Batch.session_id == session.id))
    if not n_batches:
        db.rollback()
        raise ProblemError(422, "The session has no batches: upload data before completing it",
                           title="Nothing to process", slug="session-empty")
    problem = session_span_problem(db, session.id, settings.max_session_s)
    if problem is not None:
        db.rollback()
        raise ProblemError(422, f"The session cannot be processed: {problem}", title="Session out of bounds",
                           slug="session-out-of-bounds")
    session.status = SessionStatus.queued
    session.error = None
    session.completed_at = utcnow()
    db.commit()
    enqueue(settings, session.id)
    log.info("session %s completed with %d batches; queued", session.id, n_batches)
    return session_out(db, session)


@router.post("/{session_id}/reprocess", status_code=202, response_model=SessionOut,
             responses={403: {"description": "Device tokens may not reprocess sessions"},
                        409: {"description": "The session is still receiving; complete it first"}},
             summary="Run the current algorithm again on the stored raw data (clinician/admin)")
def reprocess_session(session_id: str, db: Db, caller: Caller, settings: AppSettings) -> SessionOut:
    """Run the current algorithm again on the stored raw data."""
    with ended(db):
        return _reprocess_session(session_id, db, caller, settings)


def _reprocess_session(session_id: str, db: DbSession, caller: Principal, settings: Settings) -> SessionOut:
    require_role(caller, Role.admin, Role.clinician, action="reprocess sessions")
    session = get_session_for(db, caller, session_id, for_update=True)
    if session.status == SessionStatus.receiving:
        raise conflict("The session is still receiving; complete it first", slug="session-not-completed")
    finished = (SessionStatus.done, SessionStatus.failed)
    if session.status not in finished or not still_in_status(db, session.id, finished):
        # Queued or being processed already: 202 with the current state.
        db.rollback()
        return session_out(db, db.get(Session, session_id, populate_existing=True) or session)
    session.status = SessionStatus.queued
    session.error = None
    session.attempts = 0
    db.commit()
    enqueue(settings, session.id)
    log.info("session %s queued for reprocessing by token %s", session.id, caller.token_id)
    return session_out(db, session)
