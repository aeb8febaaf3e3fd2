"""Service settings: one `Settings` (environment prefix `CADREG_`), built by the runner and passed into
`create_app(settings)`; there is no module-level instance. Bad values fail at construction with a message naming
the setting (`settings_from(...)` turns pydantic's error into a `ConfigError`).

The algorithm's parameters travel typed: `localize_config` is a `cadreg.config.LocalizeConfig`, read from the JSON
or TOML file named by `CADREG_LOCALIZE_CONFIG` (or `cadreg serve --localize-config`), validated here at start and
handed as that object to every worker. A bad file raises `ConfigError("bad localize config <path>: <field>: <why>")`.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, SecretStr, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from cadreg.config import LocalizeConfig, config_problems as _problems, load_localize_config  # noqa: F401 (re-exported)
from cadreg.errors import ConfigError

from .codec import MAX_IMAGE_PIXELS

# zenoh locators: <protocol>/<address>[#<config>], e.g. tcp/127.0.0.1:7447, udp/[::1]:7447
_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream|unixpipe)/\S+$")


def _default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "cadreg" / "sites"


def _default_workers() -> int:
    # Two processes doubled throughput on 2 cores (DESIGN §9); more than the cores only adds memory.
    return max(1, min(2, os.cpu_count() or 1))


class Settings(BaseSettings):
    """Everything the service reads from its environment (`CADREG_<NAME>`) or command line."""

    model_config = SettingsConfigDict(env_prefix="CADREG_", extra="forbid", frozen=True)

    sites_dir: Path | None = Field(None, description="directory of site bundles (one sub-directory each); None = the demo site")
    demo_cache_dir: Path = Field(default_factory=_default_cache_dir, description="where the demo site is built when sites_dir is None")
    host: str = Field("127.0.0.1", min_length=1)
    port: int = Field(8080, ge=0, le=65535)
    workers: int = Field(default_factory=_default_workers, ge=1, le=64, description="worker processes")
    queue_depth: int = Field(4, ge=0, le=10_000, description="requests waiting for a worker beyond those running; more -> 503")
    request_timeout_s: float = Field(30.0, gt=0, le=3600, description="deadline from arrival to answer; past it -> 504")
    worker_start_timeout_s: float = Field(600.0, gt=0, description="a worker that has not loaded its sites by then is replaced")
    retry_after_s: float = Field(1.0, gt=0, le=3600, description="longest wait a 503 asks for; overload answers ask "
                                 "for the queue's expected drain time (detail.retry_after_s), the header rounds up")
    max_upload_bytes: int = Field(32 * 1024 * 1024, ge=1024, description="largest localize request body")
    max_bundle_bytes: int = Field(2 * 1024 * 1024 * 1024, ge=1024, description="largest site archive uploaded by PUT, "
                                  "and the most its bundle files may unpack to (counted while unpacking)")
    max_frame_pixels: int = Field(4096 * 3072, ge=1, le=MAX_IMAGE_PIXELS, description="most pixels of one image "
                                  "of a frame (depth, colour, labels), read from its header before any pixel is "
                                  "decoded; default 4096x3072, beyond any RGB-D sensor. Over it -> 422")
    http_header_timeout_s: float = Field(10.0, gt=0, le=600, description="a connection whose request headers are "
                                         "not complete this long after it opened (or after its last answer) is closed")
    http_keep_alive_s: float = Field(5.0, gt=0, le=600, description="an idle keep-alive connection is closed after this")
    http_body_timeout_s: float = Field(30.0, gt=0, le=3600, description="a localize request body not whole this "
                                       "long after its headers -> 408 body_timeout, and the connection closes")
    http_max_buffered_bytes: int = Field(256 * 1024 * 1024, ge=1024, description="localize request bodies held in "
                                         "memory at once over all connections; a chunk past it -> 503 overloaded, "
                                         "and the connection closes")
    http_max_header_bytes: int = Field(16 * 1024, ge=1024, le=1024 * 1024,
                                       description="largest request line + headers; more -> 400 (413 when they "
                                       "arrived in one read) and the connection closes")
    admin_token: SecretStr | None = Field(None, description="bearer token of the admin routes; None = admin routes refuse")
    zenoh_enabled: bool = True
    zenoh_mode: Literal["peer", "client", "router"] = "peer"
    zenoh_listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    zenoh_connect: list[str] = Field(default_factory=list)
    zenoh_multicast_scouting: bool = Field(False, description="off unless asked: a peer would otherwise scout the LAN")
    zenoh_gossip_scouting: bool = False
    stream_queue_per_device: int = Field(2, ge=1, le=1000, description="frames kept per streaming device; older ones are dropped")
    stream_in_flight_per_device: int = Field(2, ge=1, le=16, description="frames of one streaming device in the pool "
                                             "at once: two let a tracked 30 fps device use both workers and catch "
                                             "up after a global search; one keeps a device's answers in order")
    stream_device_ttl_s: float = Field(60.0, gt=0, le=86400, description="a streaming device idle this long is forgotten")
    stream_max_devices: int = Field(1000, ge=1, le=1_000_000, description="streaming devices tracked at once; at the cap "
                                    "the least recently seen idle one is forgotten, or a new device's frame is refused")
    stream_max_pending_bytes: int = Field(256 * 1024 * 1024, ge=1024, description="stream frame bytes waiting for the "
                                          "pool across all devices; a frame past it is refused (counted)")
    stream_pool_share: float = Field(0.5, gt=0, le=1, description="the share of the pool's capacity (workers + "
                                     "queue_depth) stream frames may fill; the rest stays for queries and HTTP")
    session_ttl_s: float = Field(60.0, gt=0, le=86400, description="a tracking session (stream device or HTTP "
                                 "session_id) unused this long is forgotten; its next frame is localized globally")
    max_sessions: int = Field(1000, ge=1, le=1_000_000, description="tracking sessions held at once (a few kB each); "
                              "at the cap the least recently used is forgotten")
    zenoh_shutdown_timeout_s: float = Field(10.0, ge=0, le=3600, description="at shutdown, how long in-flight zenoh "
                                            "queries may take to finish before they are answered 'shutting down'")
    log_requests: bool = True
    # NoDecode: the environment holds a file path, not the JSON of the model; `_localize_config` reads the file.
    localize_config: Annotated[LocalizeConfig, NoDecode] = Field(
        default_factory=LocalizeConfig,
        description="algorithm parameters for every worker; from the environment or a flag: the path of a .toml or "
        ".json file of LocalizeConfig sections (unset = the code's defaults)",
    )
    test_hooks: bool = Field(
        False, description="tests only: a frame id '__sleep__:<s>' makes the worker sleep; /debug/workers lists pids"
    )

    @field_validator("zenoh_listen", "zenoh_connect")
    @classmethod
    def _endpoints(cls, value: list[str]) -> list[str]:
        for endpoint in value:
            if not _ENDPOINT.match(endpoint):
                raise ValueError(f"{endpoint!r} is not a zenoh endpoint such as tcp/127.0.0.1:7447")
        return value

    @field_validator("sites_dir")
    @classmethod
    def _sites_dir(cls, value: Path | None) -> Path | None:
        if value is not None and not value.is_dir():
            raise ValueError(f"{value} is not a directory")
        return value

    @field_validator("localize_config", mode="before")
    @classmethod
    def _localize_config(cls, value: Any) -> Any:
        # A path is read and validated here; ConfigError is not a ValueError, so pydantic lets it through as is and
        # the start fails with the file's own message (not wrapped as "bad service settings: ...").
        if isinstance(value, str) and not value.strip():
            return LocalizeConfig()  # `CADREG_LOCALIZE_CONFIG=` (set but empty, as in a compose file) means unset
        if isinstance(value, (str, os.PathLike)):
            return load_localize_config(value)
        return value

    @model_validator(mode="after")
    def _zenoh_reachable(self) -> "Settings":
        if self.zenoh_enabled and self.zenoh_mode == "client" and not self.zenoh_connect:
            raise ValueError("zenoh_mode 'client' needs zenoh_connect endpoints (a router to talk to)")
        return self

    @model_validator(mode="after")
    def _one_body_fits_the_budget(self) -> "Settings":
        if self.http_max_buffered_bytes < self.max_upload_bytes:
            raise ValueError(f"http_max_buffered_bytes ({self.http_max_buffered_bytes}) must hold one body of "
                             f"max_upload_bytes ({self.max_upload_bytes})")
        return self

    @property
    def sites_root(self) -> Path:
        """Where bundles live: `sites_dir`, or the demo cache when serving the demo site."""
        return self.sites_dir if self.sites_dir is not None else self.demo_cache_dir

    @property
    def demo_mode(self) -> bool:
        return self.sites_dir is None


def settings_from(**overrides: Any) -> Settings:
    """Settings from the environment plus explicit overrides (None values are ignored); bad values -> ConfigError.
    `localize_config` may be given as a file path (what `--localize-config` passes) or a LocalizeConfig."""
    values = {k: v for k, v in overrides.items() if v is not None}
    try:
        return Settings(**values)
    except ValidationError as exc:
        raise ConfigError(f"bad service settings: {_problems(exc)}") from None
