"""Every setting of the job service in one place.

Each field can be given as an environment variable ``ACINOSET_<FIELD>`` (for example
``ACINOSET_DATA_DIR=/srv/acinoset``, ``ACINOSET_MAX_FRAMES=20000``); the ``acinoset serve`` and
``acinoset worker`` flags override those. Defaults suit one lab server.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

MiB = 1024 * 1024


def default_data_dir() -> Path:
    """``$XDG_DATA_HOME/acinoset`` (``~/.local/share/acinoset``): the same for ``serve`` and ``users``
    whatever the working directory."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "acinoset"


def default_workers() -> int:
    """One solve per core: a solve is single-threaded (gtsam's optimiser holds the GIL)."""
    return max(1, os.cpu_count() or 2)


class Settings(BaseSettings):
    """The service's configuration."""

    model_config = SettingsConfigDict(env_prefix="ACINOSET_", extra="ignore")

    # where and how to serve
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    data_dir: Path = Field(default_factory=default_data_dir)
    backend: Literal["embedded", "rq"] = "embedded"
    redis_url: str = "redis://127.0.0.1:6379/0"
    queue_name: str = "acinoset"
    # rq: the workers see this data dir (a volume or network disk they mount, each given it as its own
    # --data-dir): a job's input files reach them by path and their results come back on disk, not through Redis
    shared_data_dir: bool = False
    workers: int = Field(default_factory=default_workers, ge=1, le=256)  # embedded: parallel solves
    log_level: str = "info"

    # limits on what a user can ask for
    max_upload_bytes: int = Field(512 * MiB, ge=1)  # one POST /v1/jobs request, all files together
    max_frames: int = Field(50_000, ge=1)  # frames per keypoint file (7 min at 120 fps)
    max_bodyparts: int = Field(100, ge=1)  # per keypoint file, each individual's counted (memory: 3 columns each)
    max_cameras: int = Field(64, ge=1)
    max_active_jobs_per_user: int = Field(200, ge=1)  # queued + running
    max_storage_bytes_per_user: int = Field(20 * 1024 * MiB, ge=0)  # a user's job files, all jobs (0: no limit)
    max_storage_bytes: int = Field(0, ge=0)  # everyone's job files together (0: no limit but the disk)
    min_free_bytes: int = Field(1024 * MiB, ge=0)  # submissions are refused (507) below this much free disk
    page_size_max: int = Field(500, ge=1)
    # jobs may name videos on shared storage under this folder (POST /v1/jobs video_paths); unset: none
    video_root: Path | None = None
    upload_idle_timeout_seconds: float = Field(30.0, gt=0)  # an upload that sends nothing this long: 408
    upload_timeout_seconds: float = Field(1800.0, gt=0)  # a whole upload's body at most (408)
    max_receiving_uploads: int = Field(16, ge=1)  # upload bodies received at once (503 beyond)
    max_connections: int = Field(512, ge=1)  # open connections to the server (503 beyond)
    # invalid tokens one address may send in a minute; past it every call from there is 429 for the minute
    max_token_failures_per_minute: int = Field(30, ge=1)
    upload_readers: int = Field(2, ge=0, le=64)  # processes that read uploads (0: in the API process)
    upload_niceness: int = Field(5, ge=0, le=19)  # they yield the CPU to the API
    # a batch's Anipose project is read in a process of its own (service.run.batch_reader), within these (422 beyond)
    batch_read_timeout_seconds: float = Field(60.0, gt=0)  # wall clock: killed then
    batch_read_cpu_seconds: float = Field(60.0, gt=0)  # CPU time (RLIMIT_CPU)
    batch_read_memory_bytes: int = Field(2048 * MiB, ge=256 * MiB)  # address space (RLIMIT_AS)

    # running jobs
    max_attempts: int = Field(3, ge=1)  # runs of one job interrupted by crashes before it fails
    job_timeout_seconds: float = Field(6 * 3600.0, gt=0)  # longer than the longest solve
    lease_seconds: float = Field(30.0, gt=0)  # a running job whose owner stopped renewing it is lost
    heartbeat_seconds: float = Field(5.0, gt=0)  # lease renewal and RQ job monitoring interval
    progress_interval_seconds: float = Field(0.2, ge=0)  # at most one progress write per interval
    solve_niceness: int = Field(10, ge=0, le=19)  # solves yield the CPU to the API
    warm_start: bool = True  # compile the solver's kernels once in the process that forks solves

    # observability
    metrics_public: bool = True  # /metrics without a token (counts only, no job content)

    @field_validator("data_dir")
    @classmethod
    def _absolute(cls, v: Path) -> Path:
        return Path(v).expanduser().resolve()

    def make_private(self) -> None:
        """The data dir, only for the user the service runs as: this process creates files 0600 and
        directories 0700 from now on (``umask 077``: the children it forks inherit it), and the data
        dir, its job table and its jobs dir are made so if they already exist with wider rights."""
        os.umask(0o077)
        self.jobs_dir.mkdir(parents=True, exist_ok=True)
        for path, mode in ((self.data_dir, 0o700), (self.jobs_dir, 0o700), (self.db_path, 0o600)):
            if path.exists():
                path.chmod(mode)

    @field_validator("video_root")
    @classmethod
    def _real_root(cls, v: Path | None) -> Path | None:
        return None if v is None or not str(v).strip() else Path(v).expanduser().resolve()

    @property
    def db_path(self) -> Path:
        return self.data_dir / "acinoset.db"

    @property
    def jobs_dir(self) -> Path:
        return self.data_dir / "jobs"


def redacted(url: str) -> str:
    """A Redis URL fit for a log line or an answer: its password, if any, replaced by ``***``."""
    from urllib.parse import urlsplit, urlunsplit

    try:
        parts = urlsplit(url)
        if parts.password is None:
            return url
        user = parts.username or ""
        host = parts.hostname or ""
        netloc = f"{user}:***@{host}" + (f":{parts.port}" if parts.port else "")
        return urlunsplit(parts._replace(netloc=netloc))
    except ValueError:
        return "<a Redis URL>"
