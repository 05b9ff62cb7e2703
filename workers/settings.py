"""Service settings: one pydantic-settings object read from ``VOLUMESH_*`` environment variables,
shared by the gateway and the workers (the gateway imports it from here, as layers point one
way: app -> workers -> pipeline).

The defaults give the embedded mode: everything lives under ``data_dir`` (SQLite job store,
file-system broker, local storage) and no outside service is needed. Each field's docstring is
its description, which README's configuration table shows (`workers.settings_table`).
"""

from __future__ import annotations

from functools import cached_property
from pathlib import Path
from typing import Annotated

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

MiB = 1024 * 1024
GiB = 1024 * MiB


class Settings(BaseSettings):
    """Everything the gateway and the workers are configured with."""

    model_config = SettingsConfigDict(env_prefix="VOLUMESH_", extra="ignore", frozen=True,
                                      use_attribute_docstrings=True)

    data_dir: Path = Path("volumesh-data")
    """Holds everything the embedded default keeps: job store, broker files, captures, assets."""
    broker_url: str | None = None
    """Celery broker (``redis://host:6379/0``); unset: the embedded file-system broker in
    ``data_dir``."""
    database_url: str | None = None
    """SQLAlchemy URL of the job store; unset: a SQLite file in ``data_dir``."""
    storage_url: str | None = None
    """Where captures and assets are kept: ``s3://bucket/prefix`` or a local directory;
    unset: ``storage`` in ``data_dir``."""
    s3_endpoint_url: str | None = None
    """Endpoint of an S3-compatible store (MinIO, ...); unset: AWS."""
    s3_region: str = "us-east-1"
    """Region of the S3 store."""
    s3_access_key_id: str | None = None
    """Access key id for the S3 store; unset: boto3's own lookup (its environment variables,
    config files, instance role)."""
    s3_secret_access_key: SecretStr | None = None
    """Secret access key for the S3 store (kept out of logs and reprs)."""

    metrics_token: SecretStr | None = None
    """A token that reads ``/metrics`` alone (``Authorization: Bearer <token>``, as a Prometheus
    scrape config sends it); admin API keys read it too, and nothing else does."""
    cors_origins: Annotated[list[str], NoDecode] = Field(default_factory=list)
    """Origins allowed by CORS, comma separated in the environment; ``*`` allows any."""

    max_upload_bytes: int = Field(default=4 * GiB, gt=0)
    """Largest capture zip accepted."""
    max_capture_files: int = Field(default=50_000, gt=0)
    """Most entries a capture zip may hold."""
    max_unpacked_bytes: int = Field(default=16 * GiB, gt=0)
    """Largest total unpacked size of a capture zip."""
    max_compression_ratio: float = Field(default=100.0, gt=1.0)
    """Largest unpacked/packed ratio of one zip entry over 1 MiB (zip bombs exceed it)."""
    max_image_pixels: int = Field(default=25_000_000, gt=0)
    """Most pixels of one image of a capture (about twice the Azure Kinect's largest colour
    mode, 4096x3072); checked in capture.json and each image's header before any pixel is
    decoded, so reading a capture holds at most about 16 bytes per pixel of it."""
    max_json_bytes: int = Field(default=256 * 1024, gt=0)
    """Largest body of a JSON request."""
    max_frame_set_bytes: int = Field(default=64 * MiB, gt=0)
    """Largest frame-set zip a stream accepts (``PUT /api/v1/streams/{id}/frames/{index}``)."""
    stale_upload_s: float = Field(default=600.0, gt=0)
    """A partial upload untouched this long is from a gateway that died; the gateway deletes
    it while running (checked every ``stale_upload_s / 4``, at most every minute)."""
    retention_days: float | None = Field(default=None, gt=0)
    """Finished jobs and their assets are deleted this many days after they finished, and a
    capture once it is this old and no job refers to it (the gateway checks hourly); unset:
    everything is kept."""
    upload_idle_timeout_s: float = Field(default=30.0, gt=0)
    """A request body that sends no bytes for this long is answered 408 and dropped (an upload's
    partial file deleted), so a stalled client cannot hold a request open for good."""
    validation_timeout_s: float = Field(default=120.0, gt=0)
    """How long an upload waits for a worker to validate the capture."""

    task_soft_time_limit_s: int = Field(default=3300, gt=0)
    """A stage running longer is asked to stop (and fails the job)."""
    task_time_limit_s: int = Field(default=3600, gt=0)
    """A stage running longer is killed."""
    visibility_timeout_s: int = Field(default=4000, gt=0)
    """Redis: an unacknowledged task is handed to another worker after this long; a backstop,
    as leases queue a dead worker's stage again within about ``stage_lease_s``. Keep it above
    ``task_time_limit_s``."""
    task_max_retries: int = Field(default=5, ge=0)
    """Retries (with exponential back-off) of a stage that hit a transient error."""
    worker_concurrency: int = Field(default=1, gt=0)
    """Processes per worker; stages are CPU-heavy, so one per worker process is the default."""
    embedded_worker: bool = True
    """Embedded mode only: ``volumesh serve`` starts its workers beside the gateway."""
    broker_polling_interval_s: float = Field(default=0.05, gt=0)
    """Embedded file-system broker: how often an idle worker looks for a task."""
    progress_interval_s: float = Field(default=0.25, ge=0)
    """Least time between two progress writes of a stage to the job store."""
    stage_lease_s: float = Field(default=30.0, gt=0)
    """A running stage's lease: its worker renews it every ``stage_lease_s / 3``; a stage whose
    lease lapsed (worker killed, out of memory, machine lost) is queued again by the gateway,
    which looks every ``stage_lease_s / 6`` (at most every 5 s). Workers' and gateways' clocks
    must agree to well within it (NTP)."""
    stage_max_tries: int = Field(default=3, ge=1)
    """A stage whose worker stops answering this many times (its lease lapsed each time) fails
    the job, saying so."""
    worker_heartbeat_s: float = Field(default=5.0, gt=0)
    """How often a worker records that it is alive and which queues it consumes; one silent for
    three times this long counts as gone (a job waiting on its queue says so, /readyz is 503)."""

    @field_validator("metrics_token", mode="before")
    @classmethod
    def _empty_is_unset(cls, value: object) -> object:
        # docker-compose passes an unset variable as an empty one.
        return None if value == "" else value

    @field_validator("cors_origins", mode="before")
    @classmethod
    def _split_origins(cls, value: object) -> object:
        if isinstance(value, str):
            return [origin.strip() for origin in value.split(",") if origin.strip()]
        return value

    @property
    def embedded(self) -> bool:
        """True when no outside broker is configured (file-system broker in data_dir)."""
        return self.broker_url is None

    @cached_property
    def resolved_database_url(self) -> str:
        """The job store's URL: ``database_url``, else the SQLite file in ``data_dir``."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'volumesh.db').resolve()}"

    @cached_property
    def resolved_storage_url(self) -> str:
        """The storage's URL: ``storage_url``, else the ``storage`` folder in ``data_dir``."""
        return self.storage_url or str((self.data_dir / "storage").resolve())

    @property
    def broker_dir(self) -> Path:
        """The embedded file-system broker's folders."""
        return self.data_dir / "broker"

    @property
    def tmp_dir(self) -> Path:
        """Partial uploads; same file system as local storage so a finished one is renamed."""
        return self.data_dir / "tmp"

    @property
    def cache_dir(self) -> Path:
        """Worker-local copies of captures fetched from object storage."""
        return self.data_dir / "cache"


def get_settings() -> Settings:
    """Settings from the environment (a fresh object: tests change the environment)."""
    return Settings()
