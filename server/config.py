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

    @property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        self.data_dir.mkdir(parents=True, exist_ok=True)
        return f"sqlite:///{(self.data_dir / 'gaitmon.sqlite').resolve()}"

    @property
    def cors_origin_list(self) -> list[str]:
        return [o.strip().rstrip("/") for o in self.cors_origins.split(",") if o.strip()]

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
