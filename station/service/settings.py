"""Typed settings of the daemon, checked once at start-up: a bad value stops ``station serve``
before anything listens or moves, with a message naming the setting."""

from __future__ import annotations

import ipaddress
import logging
import os
import secrets
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from station.config import ServiceSection, StationConfig, default_config_path, load_config
from station.errors import ConfigError

log = logging.getLogger(__name__)

TOKEN_ENV = "STATION_TOKEN"


@dataclass(frozen=True)
class ServiceSettings:
    """Everything the daemon needs.  ``config`` carries no token (it is copied into recordings)."""

    config: StationConfig
    sim: bool
    host: str
    port: int
    token: str = field(repr=False)
    token_source: str  # "env", "config" or "generated"
    recordings_dir: Path
    database: Path
    workers: int
    config_path: Path | None = None

    @property
    def loopback_only(self) -> bool:
        return is_loopback(self.host)

    @property
    def password_n(self) -> int:
        """The scrypt cost N of the passwords this station stores: ``simulation.password_cost_log2``
        on the simulated station (--sim), else always the product's (station.lab.users.SCRYPT_N)."""
        from station.lab.users import SCRYPT_N

        sim = self.config.simulation
        return 2**sim.password_cost_log2 if self.sim and sim is not None else SCRYPT_N

    @property
    def stop_port(self) -> int | None:
        """The stop port to listen on: ``service.stop_port``; unset: ``port`` + 1 (none when the
        port is chosen by the system); 0: none."""
        wanted = self.config.service.stop_port
        if wanted is None:
            return self.port + 1 if 0 < self.port < 65535 else None
        return wanted or None


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def build_settings(cfg: StationConfig, *, sim: bool, host: str | None = None, port: int | None = None,
                   workers: int | None = None, config_path: Path | None = None,
                   env: Mapping[str, str] | None = None) -> ServiceSettings:
    """Settings from a validated configuration, the environment and command-line overrides."""
    env = os.environ if env is None else env
    svc = cfg.service
    if sim and cfg.simulation is None:
        raise ConfigError("--sim needs a configuration with a 'simulation' section")
    token, source = env.get(TOKEN_ENV, "").strip(), "env"
    if not token:
        token, source = svc.token or "", "config"
    if not token:
        if not sim:
            raise ConfigError(f"no API token: set the environment variable {TOKEN_ENV} or service.token in "
                              "the configuration (the endpoints that move the rig need it)")
        token, source = secrets.token_urlsafe(18), "generated"
    if len(token) < 8 or any(not (0x21 <= ord(c) <= 0x7E) for c in token):
        raise ConfigError(f"{TOKEN_ENV}/service.token: at least 8 printable ASCII characters without spaces expected")
    host = host or svc.host
    port = svc.port if port is None else port
    if not 0 <= port <= 65535:
        raise ConfigError(f"--port {port}: expected 0..65535")
    workers = svc.workers if workers is None else workers
    if not 0 <= workers <= 16:
        raise ConfigError(f"--workers {workers}: expected 0..16")
    rec_dir = Path(cfg.station.recordings_dir).expanduser().resolve()
    try:
        rec_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"station.recordings_dir {rec_dir}: cannot create it ({exc.strerror})") from None
    if not os.access(rec_dir, os.W_OK):
        raise ConfigError(f"station.recordings_dir {rec_dir}: not writable")
    db = Path(svc.database).expanduser()
    db = (db if db.is_absolute() else rec_dir / db).resolve()
    clean = cfg.model_copy(update={"service": ServiceSection(**{**svc.model_dump(), "token": None})})
    return ServiceSettings(config=clean, sim=sim, host=host, port=port, token=token, token_source=source,
                           recordings_dir=rec_dir, database=db, workers=workers, config_path=config_path)


def load_settings(config_path: Path | None, *, sim: bool, host: str | None = None, port: int | None = None,
                  workers: int | None = None) -> ServiceSettings:
    path = config_path or default_config_path()
    return build_settings(load_config(path), sim=sim, host=host, port=port, workers=workers, config_path=path)
