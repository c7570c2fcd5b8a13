"""The one settings object of the service, read from environment variables (pydantic-settings).

With no variables set, the service runs on its embedded default: a SQLite database and a
SQLite-backed Celery broker (kombu's SQLAlchemy transport) under ``SPINE_DATA_DIR``. Setting
``DATABASE_URL`` (PostgreSQL) and ``CELERY_BROKER_URL`` (Redis) runs the same code distributed.
"""

from __future__ import annotations

import os
import re
import socket
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from pydantic import AliasChoices, Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from services.core.webhook_policy import decode_secret, parse_allow_list

_ABSOLUTE_URI = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:\S+$")


@dataclass(frozen=True)
class DicomwebConfig:
    """Where the PACS is and how to authenticate: what ``services.dicom.dicomweb.Pacs`` connects to
    (``Settings.dicomweb`` from the SPINE_DICOMWEB_* settings, or given directly)."""

    url: str
    """DICOMweb base URL, e.g. Orthanc's ``http://host:8042/dicom-web``."""
    username: str | None = None
    password: str | None = None
    token: str | None = None
    """Bearer token (sent as ``Authorization: Bearer``); wins over username/password when both are set."""
    timeout_s: float = 10.0
    """Connect and read timeout of one DICOMweb request, s: metadata of one instance is a few kB, and a
    STOW of an SR and a figure (≈ 0.1–3 MB) takes well under a second on a hospital network; 10 s turns
    a hung PACS into a retry without holding a worker long."""


@dataclass(frozen=True)
class TcpKeepalive:
    """TCP keepalive of an idle connection (tcp(7): ``TCP_KEEPIDLE``, ``TCP_KEEPINTVL``, ``TCP_KEEPCNT``), whole
    seconds as the kernel and libpq take them: the first probe after ``idle_s`` without traffic, then one every
    ``interval_s``, the connection dropped after ``count`` unanswered ones."""

    idle_s: int
    interval_s: int
    count: int

    @classmethod
    def within(cls, timeout_s: float) -> TcpKeepalive:
        """Probes that find a dead idle connection about ``timeout_s`` after its last traffic: first after a
        third of it, then every sixth (each at least 1 s), ``idle + count · interval ≈ timeout_s``."""
        idle = max(1, int(timeout_s / 3))
        interval = max(1, int(timeout_s / 6))
        return cls(idle, interval, max(1, round((timeout_s - idle) / interval)))


class Settings(BaseSettings):
    """Every setting of the API and the worker. Names are the environment variables (README)."""

    model_config = SettingsConfigDict(env_prefix="SPINE_", extra="ignore", frozen=True)

    data_dir: Path = Field(
        default_factory=lambda: default_data_dir(),
        description="Folder of the embedded default's files (SQLite database and broker). Default: "
        "$XDG_DATA_HOME/spine, else ~/.local/share/spine: one place whatever the working directory; a relative "
        "value is made absolute once, at start.",
    )
    database_url: str | None = Field(
        None,
        validation_alias=AliasChoices("DATABASE_URL", "SPINE_DATABASE_URL"),
        description="SQLAlchemy URL of the job database, e.g. postgresql+psycopg://user@host/db. "
        "Default: sqlite:///$SPINE_DATA_DIR/spine.db.",
    )
    broker_url: str | None = Field(
        None,
        validation_alias=AliasChoices("CELERY_BROKER_URL", "SPINE_BROKER_URL"),
        description="Celery broker URL, e.g. redis://host:6379/0. "
        "Default: sqla+sqlite:///$SPINE_DATA_DIR/broker.db (no server needed).",
    )
    queue_name: str = Field("spine.jobs", description="Name of the broker queue that carries job ids.")
    db_pool_size: int = Field(10, ge=1, description="Connections kept per process (PostgreSQL).")
    db_connect_timeout_s: int = Field(
        5,
        ge=2,
        description="PostgreSQL: longest wait for a new connection, TCP handshake to authentication (libpq "
        "connect_timeout, whole seconds, at least 2). 5 s lets two lost SYNs be sent again (after 1 s and 2 s, "
        "RFC 6298's initial 1 s timeout doubled) and is the broker's connection timeout too.",
    )
    db_tcp_timeout_s: float = Field(
        30.0,
        ge=1,
        description="PostgreSQL: a connection whose server stopped answering at the TCP level (a failover, a "
        "dropped NAT entry, a cable) is closed after this: data unacknowledged this long (libpq tcp_user_timeout) "
        "or an idle connection whose keepalive probes go unanswered (first probe after a third of it). The "
        "kernel's defaults are 2 h of idleness (tcp_keepalive_time) and about 15 min of retransmissions "
        "(tcp_retries2), tcp(7). Added to SPINE_DB_STATEMENT_TIMEOUT_S it bounds the wait for any answer on an "
        "open connection (a hung pooler or proxy that acknowledges and never forwards): 503, or a worker retry.",
    )
    db_statement_timeout_s: float = Field(
        30.0,
        ge=0,
        description="PostgreSQL: a statement (lock waits included) still running after this is cancelled by the "
        "server (statement_timeout); the API answers 503, a worker retries. 0: no limit. The service's "
        "statements take milliseconds; migrations (`spine migrate`) have no limit. This plus SPINE_DB_TCP_TIMEOUT_S "
        "bounds the wait for any answer on an open connection (none when 0).",
    )
    broker_timeout_s: float = Field(
        5.0,
        gt=0,
        description="Redis broker: longest wait for a connection or for the answer to one command (redis-py "
        "socket_connect_timeout and socket_timeout). A publish that gets no answer fails after at most 3 tries "
        "(the publish retry policy), and its job is marked for the reconciler. 5 s is above a healthy Redis's "
        "longest pauses (an fsync blocking writes up to 2 s with appendfsync everysec).",
    )
    broker_tcp_timeout_s: float = Field(
        30.0,
        ge=1,
        description="Redis broker: a connection whose server stopped answering at the TCP level (a failover, a "
        "dropped NAT entry, a cable) is closed after this: data unacknowledged this long (TCP_USER_TIMEOUT) or an "
        "idle connection whose keepalive probes go unanswered (first probe after a third of it, then every sixth). "
        "Without it kombu turns redis-py's keepalive off and the kernel's defaults apply: no probe at all, about "
        "15 min of retransmissions (tcp_retries2), tcp(7). 30 s as SPINE_DB_TCP_TIMEOUT_S; redis-py's own "
        "keepalive default is a first probe after 30 s, then 3 every 5 s.",
    )
    ready_timeout_s: float = Field(
        2.0,
        gt=0,
        description="GET /readyz answers 503 when the database or the broker has not answered within this, and GET "
        "/metrics reports such a dependency down (spine_dependency_up 0). 2 s: within the 3 s the docker-compose "
        "health check waits for an answer, and Prometheus's default scrape timeout (10 s).",
    )
    reconcile_time_limit_s: float = Field(
        30.0,
        gt=0,
        description="Soft time limit of one reconciler pass (its hard limit is 5 s later): a pass is a few "
        "statements and publishes (milliseconds); one stuck on a dependency ends and the next pass, "
        "SPINE_RECONCILE_INTERVAL_S later, tries again.",
    )
    fit_time_limit_s: float = Field(
        120.0, gt=0, description="Time limit of one fit; past it the job fails with fit-timeout."
    )
    queued_timeout_s: float = Field(
        10.0,
        gt=0,
        description="A queued job whose message the broker is missing (it holds fewer messages than queued "
        "jobs) is enqueued again once it has waited this long since it was last enqueued (a job handed back "
        "while its PACS was unavailable: since it is due again); a broker that restarted has all queued jobs "
        "that are due enqueued again at once, and those not due yet enqueued for their due time. Sized for a "
        "5 ms fit: 10 s is 2000 fits of one process, far "
        "longer than a prefetched message waits.",
    )
    lease_s: float = Field(
        10.0,
        gt=0,
        description="A running job's lease: the worker renews it every third of this while the fit runs; a job "
        "whose lease expired (its worker died) is taken back by the reconciler, fenced by attempt.",
    )
    max_attempts: int = Field(
        3, ge=1, description="Runs a job may start; a job stranded in running after that many fails."
    )
    reconcile_interval_s: float = Field(
        2.0,
        gt=0,
        description="Period of the reconciler task: a stranded job is found within lease + this, a lost message "
        "within this after the broker is back.",
    )
    worker_concurrency: int = Field(0, ge=0, description="Worker processes per `spine worker`; 0 means one per core.")
    serve_worker: bool | None = Field(
        None,
        description="Whether `spine serve` starts a worker as its child process. Unset: yes on the "
        "embedded default (no DATABASE_URL), no when distributed.",
    )
    max_body_bytes: int = Field(1_048_576, ge=1024, description="Largest accepted request body (413 above).")
    max_batch_body_bytes: int = Field(
        16 * 1_048_576, ge=1024, description="Largest accepted body of POST /v1/jobs/batch (413 above)."
    )
    batch_max_jobs: int = Field(1000, ge=1, description="Most payloads in one POST /v1/jobs/batch.")
    metrics_window_s: float = Field(
        300.0, gt=0, description="Window of finished jobs over which /metrics reports duration quantiles."
    )
    log_level: str = Field("INFO", description="Log level of API and worker.")
    # Security (services/api/security.py, services/db/keys.py): API keys, headers, CORS, limits.
    api_key_cache_s: float = Field(
        5.0,
        ge=0,
        description="Seconds an API process trusts a verified key without reading it again: "
        "a revoked key is refused at most this long after `spine keys revoke`.",
    )
    max_queued_per_client: int = Field(
        2000,
        ge=0,
        description="Most jobs a client (API key name, role client) may have queued at once; "
        "past it, submissions answer 429 with Retry-After. 0: no cap. Admin keys are not capped.",
    )
    cors_origins: str = Field(
        "",
        description="Comma-separated origins (scheme://host[:port]) allowed to call the API from a browser; "
        "empty: CORS is off.",
    )
    pacs_clients: str = Field(
        "",
        description="Comma-separated client names (the names of `client` API keys) whose keys may browse the PACS "
        "(/v1/pacs: whether there is one, a study's images, one image); admin keys always may; empty: admin keys "
        "only. Any other key gets 403 `forbidden` naming the permission `pacs`.",
    )
    hsts_max_age_s: int = Field(
        0, ge=0, description="When > 0, every answer carries Strict-Transport-Security with this max-age (HTTPS only)."
    )
    metrics_require_key: bool = Field(False, description="Whether /metrics needs an admin API key.")
    access_log: bool = Field(True, description="Whether the API logs one JSON line per request.")
    # Webhooks (services/webhooks): callback_url destinations, signing and delivery.
    webhook_allowed_urls: str = Field(
        "",
        description="Comma-separated URL prefixes (scheme://host[:port][/path]) a job's callback_url must match; "
        "empty: webhooks are refused.",
    )
    webhook_secret: SecretStr | None = Field(
        None,
        description="Service-wide Standard Webhooks signing secret (whsec_ + base64, at least 16 bytes), used until "
        "API keys carry their own; unset: webhooks are refused.",
    )
    webhook_timeout_s: float = Field(10.0, gt=0, description="Time limit of one webhook delivery attempt.")
    webhook_task_margin_s: float = Field(
        70.0,
        gt=0,
        description="Time a webhook task may take beyond its attempt's SPINE_WEBHOOK_TIMEOUT_S: writing the "
        "attempt's outcome (retried in place on a database fault) and publishing the next attempt. The task's soft "
        "time limit is SPINE_WEBHOOK_TIMEOUT_S plus this, its hard limit 5 s later; an attempt cut off is swept. "
        "70 s: the in-place write retry at its longest with the default database timeouts (6 tries of up to "
        "SPINE_DB_CONNECT_TIMEOUT_S and 15.5 s of waits: 45.5 s) and one publish to a broker that does not answer "
        "(3 tries and a reconnection, about 4 times SPINE_BROKER_TIMEOUT_S plus 0.5 s: 20.5 s).",
    )
    webhook_max_attempts: int = Field(6, ge=1, le=20, description="Delivery attempts of one webhook message.")
    webhook_retry_base_s: float = Field(
        2.0, gt=0, description="Delay before the 2nd attempt; doubles at each attempt (capped at 120 s)."
    )
    webhook_sweep_after_s: float = Field(
        300.0,
        gt=0,
        description="A webhook attempt due this long ago that never happened (its message could not be "
        "published, or was lost) is published again by the reconciler; it looks back one day.",
    )

    # DICOMweb (services/dicom): a PACS to read headers from by reference and to store results in.
    dicomweb_url: str | None = Field(
        None,
        description="DICOMweb base URL of the PACS (e.g. Orthanc's http://host:8042/dicom-web). With it, a job "
        "whose study names its images by SOP Instance UID gets their spacing, orientation and geometry from "
        "their WADO-RS metadata; unset: no PACS.",
    )
    dicomweb_username: str | None = Field(None, description="HTTP basic user name for the PACS.")
    dicomweb_password: SecretStr | None = Field(None, description="HTTP basic password for the PACS.")
    dicomweb_token: SecretStr | None = Field(
        None, description="Bearer token for the PACS (wins over user name and password)."
    )
    dicomweb_store_results: bool = Field(
        False,
        description="Store each succeeded job's SR and figure (Secondary Capture) in its study by STOW-RS "
        "(needs SPINE_DICOMWEB_URL); every attempt is recorded on the job (dicom_stores). Only a job whose study has "
        "a Patient ID is stored.",
    )
    dicomweb_timeout_s: float = Field(10.0, gt=0, description="Time limit of one DICOMweb request.")
    dicomweb_max_attempts: int = Field(
        5,
        ge=1,
        le=20,
        description="STOW-RS attempts of one job's results (the delay between two: SPINE_DICOMWEB_RETRY_BASE_S, "
        "doubling, at most SPINE_DICOMWEB_RETRY_MAX_S).",
    )
    dicomweb_retry_base_s: float = Field(
        2.0,
        gt=0,
        description="Delay before the 2nd STOW-RS attempt of a job's results, and before a job whose PACS was "
        "unavailable runs again; it doubles at each attempt, up to SPINE_DICOMWEB_RETRY_MAX_S. 2 s: the default "
        "5 STOW-RS attempts span 2 + 4 + 8 + 16 = 30 s, about a PACS restart; a longer outage is left to "
        "SPINE_DICOMWEB_MAX_ATTEMPTS and SPINE_MAX_ATTEMPTS.",
    )
    dicomweb_retry_max_s: float = Field(
        60.0,
        gt=0,
        description="Longest delay between two attempts of one STOW-RS push, or two runs of a job whose PACS was "
        "unavailable (the cap of SPINE_DICOMWEB_RETRY_BASE_S's doubling).",
    )
    dicomweb_sweep_after_s: float = Field(
        300.0,
        gt=0,
        description="A STOW-RS attempt due this long ago that never happened (its message could not be published "
        "as the job ended, or was lost with the broker) is published again by the reconciler.",
    )

    # Built artifacts of succeeded jobs (services/api/artifacts.py): figures, SR, Secondary Capture, FHIR.
    artifact_cache_mb: float = Field(
        64.0,
        ge=0,
        description="Bytes (in MiB) of built artifacts of succeeded jobs (figure.png|svg, sr.dcm, figure.dcm, "
        "fhir) each API process keeps, least recently used first out, so that a second GET does not build "
        "them again; 0: no cache (an If-None-Match that matches still answers 304 without building).",
    )

    # FHIR export (services/fhir): the namespace of the patient identifiers it writes.
    patient_id_system: str | None = Field(
        None,
        description="FHIR `Identifier.system` of the Patient IDs (DICOM Patient ID (0010,0020)) the FHIR export "
        "names as each Observation's `subject`: the URI of the issuer's namespace, e.g. "
        "urn:oid:1.2.3.4.5 or https://hospital.example/patient-ids; unset: the identifier has no system.",
    )

    @field_validator("data_dir")
    @classmethod
    def _absolute_data_dir(cls, value: Path) -> Path:
        return value.expanduser().resolve()  # so that every process (worker children too) agrees

    @field_validator("patient_id_system")
    @classmethod
    def _patient_id_system(cls, value: str | None) -> str | None:
        """An absolute URI (RFC 3986 §4.3: a scheme, then no whitespace), as FHIR's ``Identifier.system``
        (``uri``) requires; empty means unset."""
        if not value:
            return None
        if not _ABSOLUTE_URI.match(value):
            raise ValueError(f"{value!r} is not an absolute URI (e.g. urn:oid:1.2.3.4.5 or https://host/path)")
        return value

    @field_validator("webhook_allowed_urls")
    @classmethod
    def _webhook_allow_list(cls, value: str) -> str:
        parse_allow_list(value)  # a bad entry stops the service at start, naming it
        return value

    @field_validator("webhook_secret")
    @classmethod
    def _webhook_secret(cls, value: SecretStr | None) -> SecretStr | None:
        if value is not None:
            decode_secret(value.get_secret_value())
        return value

    @property
    def embedded(self) -> bool:
        """True when the database is the embedded SQLite default (no DATABASE_URL set)."""
        return self.database_url is None

    @property
    def sqlalchemy_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{self.data_dir.resolve() / 'spine.db'}"

    @property
    def celery_broker_url(self) -> str:
        if self.broker_url:
            return self.broker_url
        return f"sqla+sqlite:///{self.data_dir.resolve() / 'broker.db'}"

    @property
    def pacs_client_names(self) -> frozenset[str]:
        """The client names of ``SPINE_PACS_CLIENTS``, whose keys may browse the PACS (besides admin keys)."""
        return frozenset(name.strip() for name in self.pacs_clients.split(",") if name.strip())

    @property
    def webhook_queue(self) -> str:
        """The queue of webhook deliveries (``<SPINE_QUEUE_NAME>.webhooks``): they neither wait behind
        nor delay fits."""
        return f"{self.queue_name}.webhooks"

    @property
    def dicom_queue(self) -> str:
        """The queue of STOW-RS pushes of results (``<SPINE_QUEUE_NAME>.dicom``)."""
        return f"{self.queue_name}.dicom"

    @property
    def dicomweb(self) -> DicomwebConfig | None:
        """The PACS (``SPINE_DICOMWEB_URL`` and its credentials), or None without ``SPINE_DICOMWEB_URL``:
        the one place that decides whether the service has a PACS."""
        if not self.dicomweb_url:
            return None
        return DicomwebConfig(
            url=self.dicomweb_url,
            username=self.dicomweb_username,
            password=self.dicomweb_password.get_secret_value() if self.dicomweb_password else None,
            token=self.dicomweb_token.get_secret_value() if self.dicomweb_token else None,
            timeout_s=self.dicomweb_timeout_s,
        )

    @property
    def stores_dicom_results(self) -> bool:
        """Whether succeeded jobs' SR and figure are stored in the PACS by STOW-RS
        (``SPINE_DICOMWEB_STORE_RESULTS`` with a PACS)."""
        return self.dicomweb_store_results and bool(self.dicomweb_url)

    @property
    def broker_socket_options(self) -> dict[str, object]:
        """The Redis broker's socket options (kombu's Redis transport options ``socket_keepalive`` and
        ``socket_keepalive_options``, which it passes to redis-py, which sets each of the latter with
        ``setsockopt(IPPROTO_TCP, …)``): keepalive probes and ``TCP_USER_TIMEOUT`` from
        ``SPINE_BROKER_TCP_TIMEOUT_S`` (``TcpKeepalive.within``), as ``SPINE_DB_TCP_TIMEOUT_S`` gives PostgreSQL's."""
        keepalive = TcpKeepalive.within(self.broker_tcp_timeout_s)
        return {
            "socket_keepalive": True,
            "socket_keepalive_options": {
                socket.TCP_KEEPIDLE: keepalive.idle_s,
                socket.TCP_KEEPINTVL: keepalive.interval_s,
                socket.TCP_KEEPCNT: keepalive.count,
                socket.TCP_USER_TIMEOUT: int(self.broker_tcp_timeout_s * 1000),
            },
        }

    @property
    def starts_worker(self) -> bool:
        """Whether `spine serve` starts a worker child process."""
        return self.embedded if self.serve_worker is None else self.serve_worker

    def ensure_data_dir(self) -> None:
        """Create SPINE_DATA_DIR when the embedded database or broker lives there."""
        if self.database_url is None or self.broker_url is None:
            self.data_dir.mkdir(parents=True, exist_ok=True)


def default_data_dir() -> Path:
    """``$XDG_DATA_HOME/spine``, else ``~/.local/share/spine`` (the XDG Base Directory default)."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "spine"


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings, read once from the environment."""
    return Settings()
