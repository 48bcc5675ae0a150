"""Configuration from environment variables (prefix ``GAITMON_``), with defaults that need no set-up."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """The service's settings, from ``GAITMON_*`` environment variables."""

    model_config = SettingsConfigDict(env_prefix="GAITMON_", env_file=".env", extra="ignore")

    data_dir: Path = Path("data")
    # Empty means: an SQLite file under data_dir (the embedded default).
    database_url: str = ""
    # Request bodies larger than this (after gzip decompression) get 413.
    max_body_bytes: int = 8 * 1024 * 1024
    # A request body must arrive whole within this many seconds of its headers (408 otherwise): a body that never
    # finishes would hold a request slot (GAITMON_MAX_IN_FLIGHT) for as long as the client keeps the socket open.
    body_timeout_s: float = 15.0
    max_samples_per_batch: int = 20_000
    # embedded: the API process runs queued jobs in a thread (SQLite default);
    # procrastinate: jobs go to the PostgreSQL queue and `gaitmon worker` runs them.
    job_runner: str = "auto"
    # A job whose worker stopped heart-beating for this long is taken up again.
    job_stall_seconds: int = 300
    log_level: str = "INFO"
    # text: one human-readable line per record; json: one JSON object per line (for log shippers).
    log_format: Literal["text", "json"] = "text"
    # `gaitmon serve` listens here (command-line flags win).
    host: str = "127.0.0.1"
    port: int = 8000
    # `gaitmon serve` / `create-token` bring the schema to the latest migration first.
    auto_migrate: bool = True
    # Comma-separated origins a browser app may call the API from ("*" for any); empty: CORS off.
    cors_origins: str = ""
    # Rate limits in the `limits` notation ("N/second|minute|hour", several separated by ";"); empty: no limit.
    rate_limit_per_token: str = "3000/minute"
    rate_limit_per_ip: str = "12000/minute"
    # Failed authentications (401) one client address may cause before its unknown tokens get 429.
    rate_limit_auth_failures_per_ip: str = "20/minute"
    # Where the counters live: memory:// (per process) or a `limits` storage URI such as redis://host:6379.
    rate_limit_storage: str = "memory://"
    metrics_enabled: bool = True
    # FHIR Patient.identifier system of the patients' external_id (the clinic's MRN namespace URI).
    fhir_identifier_system: str = "urn:gaitmon:patient-external-id"
    # Database pool (PostgreSQL): the API never holds a pooled connection across a thread hop, so threads that
    # talk to the database are capped at pool_size + max_overflow (see api_threads) and a request waiting longer
    # than pool_timeout_s for a connection is answered 503 + Retry-After instead of queueing.
    db_pool_size: int = 20
    db_max_overflow: int = 10
    db_pool_timeout_s: float = 5.0
    # Threads that parse and store uploaded batches (their own share of the pool's connections, see
    # upload_thread_count). Each spends ~1 ms of CPU and waits for PostgreSQL's commit; a few keep up with what one
    # process can parse, more only contend for the GIL with the event loop (30 busy threads held it off for
    # 100-300 ms at a time, and new connections waited seconds to be accepted).
    upload_threads: int = 8
    # PostgreSQL: the uploads that arrive while another group is being written share one transaction (one WAL
    # flush; each answered only after that commit). Off: one autocommitted INSERT per batch.
    upload_group_commit: bool = True
    # SQLite: how long a writer waits for the single write lock before the request is answered 503.
    sqlite_busy_timeout_s: float = 5.0
    # Requests in progress in one API process (health checks excluded) beyond which new ones get 503 at once.
    max_in_flight: int = 64
    # The seconds a 503 for transient overload tells the client to wait (Retry-After).
    retry_after_s: int = 1
    # A session whose sensors span more than this is refused at /complete and by processing.
    max_session_s: float = 12 * 3600.0

    @property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        self.data_dir.mkdir(parents=True, exist_ok=True)
        return f"sqlite:///{(self.data_dir / 'gaitmon.sqlite').resolve()}"

    @property
    def cors_origin_list(self) -> list[str]:
        """The CORS origins as a list (empty: CORS off)."""
        return [o.strip().rstrip("/") for o in self.cors_origins.split(",") if o.strip()]

    @property
    def api_threads(self) -> int:
        """Worker threads for sync routes: with the upload threads no more than the connections the pool can hand
        out at once, so a thread never waits for a connection another request holds while waiting for a thread."""
        return max(4, self.db_pool_size + self.db_max_overflow - self.upload_thread_count)

    @property
    def upload_thread_count(self) -> int:
        """Threads for batch uploads: ``upload_threads``, leaving at least 4 connections to the other routes."""
        return max(1, min(self.upload_threads, self.db_pool_size + self.db_max_overflow - 4))

    @property
    def is_sqlite(self) -> bool:
        return self.resolved_database_url.startswith("sqlite")

    @property
    def resolved_job_runner(self) -> str:
        if self.job_runner != "auto":
            return self.job_runner
        return "embedded" if self.is_sqlite else "procrastinate"


@lru_cache
def get_settings() -> Settings:
    """The settings of this process (read once)."""
    return Settings()
