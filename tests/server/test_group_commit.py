"""Group commit of uploads (server.sessions.group_commit) on PostgreSQL: concurrent rows share a transaction, each
caller learns its outcome only once that transaction committed, rows go in key order, and one failing row is
written again alone without taking the others down."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest
from sqlalchemy import Engine, create_engine, text
from sqlalchemy.exc import IntegrityError

from server.sessions.group_commit import GroupCommitter

# Shaped like the upload's statement: the key parameters it sorts by, ON CONFLICT DO NOTHING, RETURNING.
SQL = ("INSERT INTO gc_rows (session_id, sensor_id, seq) VALUES (%(b_session_id)s, %(b_sensor_id)s, %(b_seq)s) "
       "ON CONFLICT DO NOTHING RETURNING id")


@pytest.fixture
def engine(postgres_url: str) -> Iterator[Engine]:
    admin = create_engine(postgres_url)
    with admin.begin() as conn:
        conn.execute(text("DROP TABLE IF EXISTS gc_rows"))
        conn.execute(text("CREATE TABLE gc_rows (id serial PRIMARY KEY, session_id text, sensor_id text, "
                          "seq int CHECK (seq >= 0), UNIQUE (session_id, sensor_id, seq))"))
    eng = create_engine(postgres_url, isolation_level="AUTOCOMMIT", pool_size=8, max_overflow=0)
    yield eng
    eng.dispose()
    with admin.begin() as conn:
        conn.execute(text("DROP TABLE gc_rows"))
    admin.dispose()


def _row(seq: int, session: str = "s1") -> dict[str, object]:
    return {"b_session_id": session, "b_sensor_id": "L-thigh", "b_seq": seq}


def _gathered(committer: GroupCommitter, rows: list[dict[str, object]]) -> dict[int, bool | Exception]:
    """Every row submitted from a thread of its own while the committer is busy, so that they gather."""
    out: dict[int, bool | Exception] = {}

    def one(i: int) -> None:
        try:
            out[i] = committer.insert(SQL, rows[i])
        except Exception as exc:  # noqa: BLE001 - the test looks at it
            out[i] = exc

    with committer._writing:  # a group "being written": the rows below gather into the next one
        threads = [threading.Thread(target=one, args=(i,)) for i in range(len(rows))]
        for th in threads:
            th.start()
        deadline = time.monotonic() + 10
        while (committer._open is None or len(committer._open.rows) < len(rows)) and time.monotonic() < deadline:
            time.sleep(0.005)
        assert not out, "nothing may be answered before its group is written"
    for th in threads:
        th.join(10)
    return out


def _stored(engine: Engine) -> list[tuple[int, str, int]]:
    with engine.connect() as conn:
        return [tuple(r) for r in conn.execute(text("SELECT id, session_id, seq FROM gc_rows ORDER BY id"))]


def test_concurrent_rows_share_one_transaction_written_in_key_order(engine: Engine) -> None:
    committer = GroupCommitter(engine)
    rows = [_row(seq) for seq in (4, 2, 0, 3, 1)] + [_row(2)]  # the last: a replay of a row in the same group
    out = _gathered(committer, rows)
    assert (committer.groups, committer.rows) == (1, 6)
    assert [out[i] for i in range(6)] == [True] * 5 + [False]
    stored = _stored(engine)
    assert [seq for _, _, seq in stored] == [0, 1, 2, 3, 4]  # ids handed out in key order
    # Committed when answered: a new connection sees every row.
    assert len(stored) == 5


def test_a_lone_row_is_written_at_once_and_a_replay_stores_nothing(engine: Engine) -> None:
    committer = GroupCommitter(engine)
    assert committer.insert(SQL, _row(7)) is True
    assert committer.insert(SQL, _row(7)) is False
    assert (committer.groups, committer.rows) == (2, 2)
    assert [seq for _, _, seq in _stored(engine)] == [7]


def test_a_failing_row_fails_alone_and_the_rest_of_its_group_is_stored(engine: Engine) -> None:
    committer = GroupCommitter(engine)
    rows = [_row(0), _row(-1), _row(1)]  # seq -1 violates the CHECK: the group's transaction fails
    out = _gathered(committer, rows)
    assert out[0] is True and out[2] is True
    assert isinstance(out[1], IntegrityError)  # as SQLAlchemy would have raised it
    assert [seq for _, _, seq in _stored(engine)] == [0, 1]


def test_ungrouped_writes_each_row_alone(engine: Engine) -> None:
    committer = GroupCommitter(engine, grouped=False)
    assert [committer.insert(SQL, _row(s)) for s in (1, 0, 1)] == [True, True, False]
    assert committer.groups == 0
    assert [seq for _, _, seq in _stored(engine)] == [1, 0]
