"""PostgreSQL: the guarded INSERTs of one API process's concurrent uploads written in one transaction (group
commit), straight on the driver.

An upload thread hands its statement to :meth:`GroupCommitter.insert` and learns whether its row was stored only
after the transaction holding the row committed: a 201 is as durable when it is sent as with one autocommitted
INSERT per batch. What the group saves: one WAL flush and one pipeline of statements for all its rows instead of
one each, and SQLAlchemy's per-statement machinery (the SQL is compiled once; psycopg runs it).

No timer: a group is whatever arrived while the previous group was being written, so under light load an upload
is written at once, alone, and under saturation a group holds up to one row per upload thread. Each row keeps every
check of the single statement (:func:`server.sessions.ingest.guarded_insert`: session receiving, token live, session
visible to the caller, ON CONFLICT DO NOTHING); a row that stored nothing is answered by the caller's
replay/409/401/404 path. Rows are written in key order, so two processes' groups wait for each other's unique keys
(a batch replayed while its first copy is in flight elsewhere) in one order and never deadlock. A group whose
transaction fails is rolled back and each of its rows is written again on its own, so one row's trouble is never
another's.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import psycopg
from sqlalchemy import Engine, Executable
from sqlalchemy.exc import DBAPIError

log = logging.getLogger("gaitmon.ingest")

Params = dict[str, Any]


def driver_sql(engine: Engine, stmt: Executable) -> tuple[str, Params]:
    """The statement compiled for the engine's driver (psycopg's ``%(name)s`` placeholders) and the values it binds
    itself (literals such as the status compared with), as plain values."""
    compiled = stmt.compile(dialect=engine.dialect)
    if compiled.literal_execute_params or compiled.post_compile_params:
        raise ValueError("statements with expanding parameters need SQLAlchemy's execution")
    fixed = {k: v.value if isinstance(v, Enum) else v for k, v in compiled.params.items() if v is not None}
    return compiled.string, fixed


@dataclass
class _Group:
    rows: list[tuple[str, Params]] = field(default_factory=list)
    outcomes: list[bool | BaseException] = field(default_factory=list)
    done: threading.Event = field(default_factory=threading.Event)


def _key(params: Params) -> tuple[str, str, int]:
    return (params["b_session_id"], params["b_sensor_id"], params["b_seq"])


class GroupCommitter:
    """Writes guarded INSERTs (``RETURNING`` a row when stored) of concurrent uploads in shared transactions."""

    def __init__(self, engine: Engine, *, grouped: bool = True) -> None:
        self._engine = engine
        self._grouped = grouped
        self._lock = threading.Lock()  # guards _open
        self._writing = threading.Lock()  # one group written at a time: the next one gathers meanwhile
        self._open: _Group | None = None
        # Groups and rows written (tests and benchmarks read them).
        self.groups = 0
        self.rows = 0

    def insert(self, sql: str, params: Params) -> bool:
        """Run one guarded INSERT; True when it stored its row, once the transaction holding it committed."""
        if not self._grouped:
            return self._alone(sql, params)
        with self._lock:
            group = self._open
            leader = group is None
            if leader:
                group = self._open = _Group()
            index = len(group.rows)
            group.rows.append((sql, params))
        if leader:
            try:
                with self._writing:
                    with self._lock:
                        self._open = None  # later arrivals gather into the next group
                    group.outcomes = self._write(group.rows)
            except BaseException as exc:  # noqa: BLE001 - handed to every member, raised below
                group.outcomes = [exc] * len(group.rows)
            finally:
                group.done.set()
        else:
            group.done.wait()
        outcome = group.outcomes[index]
        if isinstance(outcome, BaseException):
            raise outcome
        return outcome

    def _write(self, rows: list[tuple[str, Params]]) -> list[bool | BaseException]:
        self.groups += 1
        self.rows += len(rows)
        if len(rows) == 1:
            return [self._catching(*rows[0])]
        order = sorted(range(len(rows)), key=lambda i: _key(rows[i][1]))
        try:
            stored = self._transaction([rows[i] for i in order])
        except psycopg.Error as exc:
            log.info("upload: group of %d batches failed (%s); each on its own", len(rows), type(exc).__name__)
            return [self._catching(sql, params) for sql, params in rows]
        out: list[bool | BaseException] = [False] * len(rows)
        for pos, i in enumerate(order):
            out[i] = stored[pos]
        return out

    def _catching(self, sql: str, params: Params) -> bool | BaseException:
        try:
            return self._alone(sql, params)
        except Exception as exc:  # noqa: BLE001 - this row's answer (a 5xx/503), not the group's
            return exc

    def _transaction(self, rows: list[tuple[str, Params]]) -> list[bool]:
        raw = self._engine.raw_connection()
        try:
            conn: psycopg.Connection = raw.driver_connection  # type: ignore[assignment]
            with conn.transaction(), conn.cursor() as cur:
                if len({sql for sql, _ in rows}) == 1:
                    # One pipeline: every INSERT sent before the first result is read.
                    cur.executemany(rows[0][0], [params for _, params in rows], returning=True)
                    stored = []
                    while True:
                        stored.append(cur.fetchone() is not None)
                        if not cur.nextset():
                            break
                    return stored
                out = []
                for sql, params in rows:  # callers of different roles: statements differ
                    cur.execute(sql, params)
                    out.append(cur.fetchone() is not None)
                return out
        except psycopg.Error:
            if raw.driver_connection is None or raw.driver_connection.broken:
                raw.invalidate()
            raise
        finally:
            raw.close()

    def _alone(self, sql: str, params: Params) -> bool:
        """One autocommitted INSERT; once more on a new connection when the pooled one turned out dead (the upload
        engine has no pre-ping). Safe: had the first attempt stored the batch, the second stores nothing and the
        caller's full checks answer it as a replay."""
        for attempt in (1, 2):
            raw = self._engine.raw_connection()
            try:
                conn: psycopg.Connection = raw.driver_connection  # type: ignore[assignment]
                with conn.cursor() as cur:
                    cur.execute(sql, params)
                    return cur.fetchone() is not None
            except psycopg.Error as exc:
                dead = conn.broken
                if dead:
                    raw.invalidate()
                if not dead or attempt == 2:
                    # As SQLAlchemy would raise it: an OperationalError is answered 503 + Retry-After.
                    raise DBAPIError.instance(sql, params, exc, psycopg.Error, hide_parameters=True,
                                              connection_invalidated=dead) from exc
                log.warning("upload: pooled connection was dead (%s); once more on a new one", type(exc).__name__)
            finally:
                raw.close()
        raise AssertionError("unreachable")
