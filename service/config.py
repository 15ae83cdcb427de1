"""The plant configuration file (YAML) and the service settings (environment).

The plant file lists units and loops (and, for a PI Web API historian, the
loop tag of each PI point)::

    units:
      - id: column
        name: Distillation column
    loops:
      - id: FIC-101
        name: Reflux flow
        unit: column
        tags: {op: FIC101.OP, pv: FIC101.PV, sp: FIC101.SP, mode: FIC101.MODE}
        mode_map: {16: manual, 8: auto, 4: cascade}
        ranges: {op: [0, 100], pv: [0, 40]}
        ts: 1.0
        controller: {type: PI, Kc: 0.5, Ti: 8, action: reverse}
        process_type: self-regulating
        valve_asset: FV-101
        importance: high
    pi_points:
      '\\\\PISRV01\\FIC101.PV': FIC101.PV
    cmms:
      sap_pm: {planning_plant: "1000", work_center: INST-01}
      maximo: {siteid: BEDFORD, orgid: EAGLENA}

Signals are converted to % of span with ``ranges`` before analysis, so S and J
come out in % of valve travel.  A unit may carry its process matrix
(:class:`UnitProcessConfig`) for the limit-cycle prediction of its loops.  The
CMMS fields of tickets (:class:`CmmsConfig`: SAP PM planning plant, work centre
and catalogue codes; Maximo site and organisation) are set for the plant, a
unit or a loop; the most specific wins, field by field.  An
invalid file is refused at start with the key path (``loops[2].tags.pv``) and
the reason.
"""

from __future__ import annotations

import base64
import json
import re
import secrets
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    SecretStr,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError

from analytics.errors import AnalyticsError
from analytics.kpi import Mode
from analytics.lti import TransferFunction
from analytics.types import ProcessType
from service.prediction import ModelError, check_matrix

__all__ = [
    "ConfigError",
    "ControllerConfig",
    "LoopConfig",
    "PlantConfig",
    "Settings",
    "UnitConfig",
    "UnitProcessConfig",
    "load_plant_config",
]

Importance = Literal["low", "medium", "high", "critical"]


class ConfigError(ValueError):
    """The plant configuration is invalid; the message names the key path."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ControllerConfig(_Strict):
    """The loop's controller as tuned in the DCS (ideal PI/PID form)."""

    type: Literal["P", "PI", "PID"] = "PI"
    Kc: float = Field(gt=0, description="controller gain (OP % per PV % of span)")
    Ti: float | None = Field(default=None, gt=0, description="integral time, s")
    Td: float = Field(default=0.0, ge=0, description="derivative time, s")
    action: Literal["reverse", "direct"] = "reverse"

    @model_validator(mode="after")
    def _integral_needs_ti(self) -> ControllerConfig:
        if self.type in ("PI", "PID") and self.Ti is None:
            raise ValueError(f"a {self.type} controller needs Ti")
        return self


class TagsConfig(_Strict):
    """Historian / connector tag names of the loop's signals."""

    op: str | None = None
    pv: str | None = None
    sp: str | None = None
    mv: str | None = None
    mode: str | None = Field(
        default=None, description="the controller's mode (raw values as the DCS reports "
        "them; the loop's mode_map names them)")

    @model_validator(mode="after")
    def _op_or_pv(self) -> TagsConfig:
        if self.op is None and self.pv is None:
            raise ValueError("a loop needs at least an op or a pv tag")
        return self

    def items(self) -> list[tuple[str, str]]:
        """(signal, tag) pairs of the tags that are set."""
        return [(s, t) for s in ("op", "pv", "sp", "mv", "mode")
                if (t := getattr(self, s)) is not None]


def _code(value: str | None, what: str, pattern: str, form: str) -> str | None:
    """``value`` if it is a valid CMMS code (``pattern``), else an error saying the form."""
    if value is not None and not re.fullmatch(pattern, value):
        raise ValueError(f"{what} must be {form}, got {value!r}")
    return value


class SapPmConfig(_Strict):
    """SAP PM fields of the M2 notifications of a loop's tickets (BAPI_ALM_NOTIF_CREATE)."""

    planning_plant: str | None = Field(default=None, description="IWERK: maintenance "
                                       "planning plant, 4 letters or digits")
    work_center: str | None = Field(default=None, description="ARBPL: main work centre, "
                                    "1-8 characters")
    code_group: str | None = Field(default=None, description="coding code group (QMGRP)")
    coding: str | None = Field(default=None, description="coding code (QMCOD)")
    damage_code_group: str | None = None
    damage_code: str | None = None
    cause_code_group: str | None = None
    cause_code: str | None = None
    object_part_code_group: str | None = None
    object_part_code: str | None = None

    @field_validator("planning_plant")
    @classmethod
    def _plant(cls, value: str | None) -> str | None:
        return _code(value, "SAP planning plant (IWERK)", r"[A-Z0-9]{4}",
                     "4 upper-case letters or digits, e.g. '1000'")

    @field_validator("work_center")
    @classmethod
    def _work_center(cls, value: str | None) -> str | None:
        return _code(value, "SAP work centre (ARBPL)", r"[A-Z0-9_/-]{1,8}",
                     "1-8 upper-case letters, digits, _ / or -")

    @field_validator("code_group", "damage_code_group", "cause_code_group",
                     "object_part_code_group")
    @classmethod
    def _group(cls, value: str | None) -> str | None:
        return _code(value, "an SAP catalogue code group", r"[A-Z0-9_-]{1,8}",
                     "1-8 upper-case letters, digits, _ or -")

    @field_validator("coding", "damage_code", "cause_code", "object_part_code")
    @classmethod
    def _catalogue_code(cls, value: str | None) -> str | None:
        return _code(value, "an SAP catalogue code", r"[A-Z0-9_-]{1,4}",
                     "1-4 upper-case letters, digits, _ or -")

    @model_validator(mode="after")
    def _codes_with_groups(self) -> SapPmConfig:
        for kind in ("", "damage_", "cause_", "object_part_"):
            group, code = f"{kind}code_group", ("coding" if not kind else f"{kind}code")
            if (getattr(self, group) is None) != (getattr(self, code) is None):
                raise ValueError(f"{group} and {code} go together: a catalogue code is "
                                 "read within its code group")
        return self


class MaximoConfig(_Strict):
    """Maximo fields of the work orders of a loop's tickets (``mxwo``)."""

    siteid: str | None = Field(default=None, description="SITEID, 1-8 characters")
    orgid: str | None = Field(default=None, description="ORGID, 1-8 characters")

    @field_validator("siteid", "orgid")
    @classmethod
    def _maximo_id(cls, value: str | None) -> str | None:
        return _code(value, "a Maximo site or organisation id", r"[A-Z0-9_-]{1,8}",
                     "1-8 upper-case letters, digits, _ or -")


class CmmsConfig(_Strict):
    """CMMS fields of tickets, for the plant, a unit or a loop (the most specific wins,
    field by field)."""

    sap_pm: SapPmConfig = Field(default_factory=SapPmConfig)
    maximo: MaximoConfig = Field(default_factory=MaximoConfig)

    def over(self, base: CmmsConfig) -> CmmsConfig:
        """These settings, with ``base``'s where these leave a field unset."""
        mine = self.model_dump(exclude_none=True)
        merged = base.model_dump(exclude_none=True)
        for system, fields in mine.items():
            merged.setdefault(system, {}).update(fields)
        return CmmsConfig.model_validate(merged)


def _nul_at(value: Any, where: str = "") -> str | None:
    """Where in ``value`` (a key or a string, nested dicts and lists searched) a NUL
    character stands; None if nowhere."""
    if isinstance(value, str):
        return where or "the value" if "\x00" in value else None
    if isinstance(value, dict):
        items: list[tuple[str, Any]] = []
        for key, item in value.items():
            if isinstance(key, str) and "\x00" in key:
                return f"{where}.{key!r}".lstrip(".")
            items.append((f"{where}.{key}".lstrip("."), item))
        return next((found for path, item in items if (found := _nul_at(item, path))), None)
    if isinstance(value, list | tuple):
        return next((found for k, item in enumerate(value)
                     if (found := _nul_at(item, f"{where}[{k}]"))), None)
    return None


class LoopConfig(_Strict):
    """One control loop."""

    @model_validator(mode="before")
    @classmethod
    def _no_nul(cls, data: Any) -> Any:
        """A NUL character fits no text field of the store (PostgreSQL refuses it in text,
        and in JSON once it is read as such): refused with where it stands."""
        where = _nul_at(data)
        if where is not None:
            raise ValueError(f"text cannot hold a NUL (0x00) character: at {where}")
        return data

    id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.:-]+$")
    name: str = ""
    unit: str | None = None
    tags: TagsConfig
    ranges: dict[Literal["op", "pv", "sp", "mv"], tuple[float, float]] = Field(
        default_factory=dict
    )
    ts: float = Field(gt=0, description="sampling interval, s")
    controller: ControllerConfig | None = None
    process_type: ProcessType | None = None
    process_model: dict[str, Any] | None = None
    pv_limits: tuple[float, float] | None = Field(
        default=None, description="PV's operating limits (PV units): the KPIs count the "
        "time within them")
    mode_map: dict[float, Mode] | None = Field(
        default=None, description="raw value of the mode tag -> auto, cascade or manual "
        "(e.g. Foundation Fieldbus MODE_BLK: 16 manual, 8 auto, 4 cascade); other values "
        "count as unknown")
    valve_asset: str | None = None
    location: str | None = None
    importance: Importance = "medium"
    cmms: CmmsConfig | None = Field(default=None, description="CMMS fields of its tickets "
                                    "(over its unit's and the plant's)")

    @field_validator("ranges")
    @classmethod
    def _increasing(
        cls, ranges: dict[str, tuple[float, float]]
    ) -> dict[str, tuple[float, float]]:
        for signal, (low, high) in ranges.items():
            if not high > low:
                raise ValueError(f"range of {signal} must have high > low, got [{low}, {high}]")
        return ranges

    @field_validator("process_model")
    @classmethod
    def _transfer_function(cls, model: dict[str, Any] | None) -> dict[str, Any] | None:
        """A process model is a whole transfer function, as in the ``loopwatch predict``
        model file (a fopdt without its gain K gives no gain to size J with), or the
        dead time alone, ``{theta}`` (s), for the Harris index."""
        if model is None:
            return None
        if set(model) == {"theta"}:
            theta = model["theta"]
            number = isinstance(theta, int | float) and not isinstance(theta, bool)
            if not (number and 0 <= theta < float("inf")):
                raise ValueError("theta (the dead time, s) must be a finite number >= 0, "
                                 f"got {theta!r}")
            return model
        try:
            TransferFunction.from_dict(model)
        except AnalyticsError as exc:
            raise ValueError(f"{exc} (a transfer function as in the loopwatch predict model "
                             "file, or {theta} alone for the dead time)") from None
        return model

    @field_validator("pv_limits")
    @classmethod
    def _limits_increasing(
        cls, limits: tuple[float, float] | None
    ) -> tuple[float, float] | None:
        if limits is not None and not limits[1] > limits[0]:
            raise ValueError(f"pv_limits must have high > low, got [{limits[0]}, {limits[1]}]")
        return limits

    @model_validator(mode="after")
    def _mode_tag_and_map(self) -> LoopConfig:
        if (self.tags.mode is None) != (self.mode_map is None):
            raise ValueError("a mode tag and a mode_map go together (the map names the "
                             "tag's raw values auto, cascade or manual)")
        return self


class UnitProcessConfig(_Strict):
    """The unit's process as an n x n transfer-function matrix, for limit-cycle prediction.

    ``matrix[i][j]`` is the transfer function from the valve (OP) of ``loops[j]``
    to the PV of ``loops[i]``, in % of span per % of OP span, with entries as in
    the ``loopwatch predict`` model file: ``{type: fopdt, K, tau, theta}``,
    ``{type: integrating, K, theta}``, ``{num, den, theta}`` or null (no coupling).
    """

    loops: list[str] = Field(min_length=1, description="loop ids: the order of rows and columns")
    matrix: list[list[dict[str, Any] | None]]

    @model_validator(mode="after")
    def _square_transfer_functions(self) -> UnitProcessConfig:
        _no_duplicates(self.loops, "loops in the process matrix")
        try:
            n = check_matrix(self.matrix, "matrix")
        except ModelError as exc:
            raise ValueError(str(exc)) from None
        if n != len(self.loops):
            raise ValueError(
                f"matrix is {n} x {n} but 'loops' names {len(self.loops)} loops "
                "(one row and column per loop)"
            )
        return self


class UnitConfig(_Strict):
    """A process unit: loops that interact (a column, a reactor)."""

    id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.:-]+$")
    name: str = ""
    process: UnitProcessConfig | None = None
    cmms: CmmsConfig | None = Field(default=None, description="CMMS fields of the tickets of "
                                    "its loops (over the plant's)")


class PlantConfig(_Strict):
    """The whole plant file."""

    units: list[UnitConfig] = Field(default_factory=list)
    loops: list[LoopConfig] = Field(default_factory=list)
    connectors: dict[str, Any] = Field(default_factory=dict)
    cmms: CmmsConfig = Field(default_factory=CmmsConfig,
                             description="CMMS fields of every ticket, unless a unit or loop "
                                         "sets them")
    pi_points: dict[str, str] = Field(
        default_factory=dict,
        description="PI point or AF attribute, by the Path or Name a PI Web API answer gives "
                    "it, -> the loop tag its values are stored as (POST /api/v1/ingest)")

    @model_validator(mode="after")
    def _consistent(self) -> PlantConfig:
        unit_ids = [u.id for u in self.units]
        _no_duplicates(unit_ids, "units")
        _no_duplicates([loop.id for loop in self.loops], "loops")
        tags = [tag for loop in self.loops for _, tag in loop.tags.items()]
        _no_duplicates(tags, "tags (a tag belongs to one loop)")
        for point, tag in self.pi_points.items():
            if tag not in tags:
                raise ValueError(
                    f"pi_points[{point!r}]: {tag!r} is not a tag of any loop; map the PI point "
                    "to one of the loops' tags")
        for i, loop in enumerate(self.loops):
            if loop.unit is not None and loop.unit not in unit_ids:
                raise ValueError(
                    f"loops[{i}].unit: unknown unit {loop.unit!r} (units: {', '.join(unit_ids)})"
                )
        unit_of = {loop.id: loop.unit for loop in self.loops}
        for i, unit in enumerate(self.units):
            for j, loop_id in enumerate(unit.process.loops if unit.process else ()):
                if unit_of.get(loop_id) != unit.id:
                    raise ValueError(
                        f"units[{i}].process.loops[{j}]: {loop_id!r} is not a loop of unit "
                        f"{unit.id!r}"
                    )
        return self

    def cmms_of(self, loop_id: str) -> CmmsConfig:
        """The CMMS fields of the tickets of loop ``loop_id``: the loop's over its unit's
        over the plant's (the plant's for a loop no longer configured)."""
        cmms = self.cmms
        loop = next((x for x in self.loops if x.id == loop_id), None)
        if loop is None:
            return cmms
        unit = next((u for u in self.units if u.id == loop.unit), None)
        for level in (unit.cmms if unit is not None else None, loop.cmms):
            if level is not None:
                cmms = level.over(cmms)
        return cmms

    def loop(self, loop_id: str) -> LoopConfig:
        """The loop with id ``loop_id`` (KeyError if absent)."""
        for loop in self.loops:
            if loop.id == loop_id:
                return loop
        raise KeyError(loop_id)


def _no_duplicates(values: list[str], what: str) -> None:
    seen: set[str] = set()
    for v in values:
        if v in seen:
            raise ValueError(f"duplicate {what}: {v!r}")
        seen.add(v)


def _key_path(location: tuple[int | str, ...]) -> str:
    path = ""
    for part in location:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path or "(top level)"


def parse_plant_config(data: Any, source: str = "configuration") -> PlantConfig:
    """Validate already-parsed YAML/JSON data; errors name the key path."""
    try:
        return PlantConfig.model_validate(data)
    except ValidationError as exc:
        lines = [
            f"{_key_path(tuple(e['loc']))}: {e['msg']}"
            + (f" (got {e['input']!r})" if e["type"] != "missing" and _short(e["input"]) else "")
            for e in exc.errors()
        ]
        details = "\n  ".join(lines)
        raise ConfigError(f"{source}: invalid plant configuration:\n  {details}") from None


def _short(value: Any) -> bool:
    return isinstance(value, str | int | float | bool) and len(repr(value)) < 60


def load_plant_config(path: str | Path) -> PlantConfig:
    """Read and validate a plant YAML file."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    return parse_plant_config(data if data is not None else {}, str(path))


DEV_API_KEY = "dev-insecure-key"
KNOWN_DEFAULT_SECRETS = frozenset({
    DEV_API_KEY, "changeme", "change-me", "secret", "password", "admin", "postgres",
    "loopwatch", "example", "test",
})
"""Secrets that come with examples and tutorials: refused outside development."""


def _comma_separated(value: Any) -> Any:
    """``a,b`` from the environment as ``["a", "b"]`` (JSON lists are taken as they are)."""
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("["):
            return json.loads(text)
        return [part.strip() for part in text.split(",") if part.strip()]
    return value


class Settings(BaseSettings):
    """Service settings from the environment (prefix ``LOOPWATCH_``).

    Secrets (the bootstrap key, the database URL with its password) are
    :class:`~pydantic.SecretStr`, so a logged or printed ``Settings`` shows
    ``**********`` instead.  Outside ``development`` a secret left at a known
    default, and a CORS wildcard, are refused at start; the refusal never shows the
    input (``hide_input_in_errors``), as it would hold the secrets.
    """

    model_config = SettingsConfigDict(env_prefix="LOOPWATCH_", extra="ignore",
                                      hide_input_in_errors=True)

    environment: Literal["development", "production"] = "development"
    data_dir: Path = Path("data")
    database_url: SecretStr | None = Field(
        default=None, description="SQLAlchemy URL; default: SQLite file in data_dir"
    )
    api_key: SecretStr | None = Field(
        default=None, description="bootstrap admin key; generated and printed when unset"
    )
    analysis_interval_s: float = Field(default=60.0, gt=0)
    window_s: float = Field(default=3600.0, gt=0, description="analysis window length, s")
    buffer_horizon_s: float = Field(default=4 * 3600.0, gt=0)
    sample_retention_days: float = Field(default=30.0, gt=0)
    ticket_confirmations: int = Field(
        default=2, ge=1,
        description="stiction findings on windows that do not overlap, with no other finding "
        "in between, that open a ticket",
    )
    workers: int = Field(default=2, ge=1, description="analysis process-pool size")
    analysis_timeout_s: float = Field(default=60.0, gt=0)
    webhook_url: str | None = Field(
        default=None, description="where ticket and alarm events are POSTed (Standard Webhooks)")
    webhook_secret: SecretStr | None = Field(
        default=None, description="the webhook's signing secret: whsec_ and base64 key bytes")
    smtp_host: str | None = Field(default=None, description="SMTP server for e-mail events")
    smtp_port: int = Field(default=25, gt=0, lt=65536)
    email_from: str = "loopwatch@localhost"
    email_to: Annotated[list[str], NoDecode, BeforeValidator(_comma_separated)] = Field(
        default_factory=list, description="recipients of e-mail events (comma-separated)")
    access_log: Literal["failed", "all", "off"] = Field(
        default="failed", description="console lines for HTTP requests: those answered "
                                      "400 or above, all, or off")
    host: str = "127.0.0.1"
    log_format: Literal["text", "json"] = Field(
        default="text", description="console log lines: text, or JSON objects with the "
                                    "request id (for a log collector)")
    port: int = Field(default=8000, ge=0, lt=65536)
    cors_origins: Annotated[list[str], NoDecode, BeforeValidator(_comma_separated)] = Field(
        default_factory=list,
        description="origins (scheme://host[:port]) whose pages may call the API; "
                    "empty: same origin only",
    )
    max_body_bytes: int = Field(
        default=20 * 1024 * 1024, gt=0, description="largest request body accepted, bytes"
    )
    max_batch_samples: int = Field(
        default=200_000, gt=0, description="most samples taken in one ingest batch"
    )
    ingest_concurrency: int = Field(
        default=1, ge=1,
        description="ingest batches and CSV uploads validated and written at once by one "
                    "process (SQLite writes one at a time anyway; more may help PostgreSQL)",
    )
    rate_limit_per_s: float = Field(
        default=20.0, gt=0, description="requests per second sustained by one API key"
    )
    rate_limit_burst: int = Field(
        default=100, ge=1, description="requests one API key may send at once above the rate"
    )
    spool_max_samples: int = Field(
        default=2_000_000, ge=0,
        description="samples held in memory while the store is unreachable (0: none); "
                    "17-40 bytes each",
    )
    spool_retry_s: float = Field(
        default=5.0, gt=0, description="pause between attempts to write the spool, s"
    )
    auth_failure_burst: int = Field(
        default=20, ge=1,
        description="failed authentications one client address may make at once",
    )
    auth_failure_per_s: float = Field(
        default=1.0, gt=0,
        description="failed authentications per second sustained from one client address",
    )
    analyses_per_key: int = Field(
        default=1, ge=1,
        description="expensive analyses (model check, advice, unit diagnosis and "
                    "prediction) one API key may run at once",
    )
    analysis_processes: int = Field(
        default=1, ge=1,
        description="processes that run the API's expensive analyses (apart from the "
                    "request threads, so their compiled kernels hold no lock the other "
                    "requests need); twice as many may be admitted at once, one waiting "
                    "per process, the rest get 503",
    )
    analysis_retry_s: float = Field(
        default=5.0, gt=0, description="Retry-After of a key refused an analysis, s")
    header_timeout_s: float = Field(
        default=10.0, gt=0, description="time a client has to send a request's headers, s")
    body_timeout_s: float = Field(
        default=30.0, gt=0,
        description="longest pause while a client sends a request body, s")
    keep_alive_s: float = Field(
        default=5.0, gt=0, description="idle keep-alive connections are closed after, s")
    forwarded_allow_ips: str = Field(
        default="127.0.0.1",
        description="proxies (comma-separated addresses, or *) whose X-Forwarded-For "
                    "names the client: the address failed authentications count against")
    max_connections: int = Field(
        default=1000, ge=1,
        description="open connections (and requests) at once; beyond, new requests get 503")
    read_cache_s: float = Field(
        default=2.0, ge=0,
        description="longest the loop list, the bad-actor ranking and the alarm list "
                    "computed for one request are given to others, s (this process's "
                    "writes show at once; "
                    "0: every request reads the store)",
    )
    auth_cache_s: float = Field(
        default=5.0, ge=0,
        description="a key the store confirmed this recently is admitted without asking it "
                    "again, s; a key revoked through this process is refused at once, one "
                    "revoked by another replica within this time (0: every request asks)",
    )
    auth_outage_grace_s: float = Field(
        default=3600.0, ge=0,
        description="while the store is unreachable, keys confirmed this recently still "
                    "authenticate, s",
    )

    @field_validator("cors_origins")
    @classmethod
    def _origins(cls, origins: list[str]) -> list[str]:
        for origin in origins:
            if origin != "*" and not re.fullmatch(r"https?://[^/\s?#]+", origin):
                raise ValueError(
                    f"CORS origin {origin!r} must be scheme://host[:port] "
                    "(no path, no trailing slash)"
                )
        return origins

    @model_validator(mode="after")
    def _notification_channels(self) -> Settings:
        if self.webhook_url is not None:
            if not self.webhook_url.startswith(("http://", "https://")):
                raise ValueError(f"LOOPWATCH_WEBHOOK_URL must start with http:// or https://, "
                                 f"got {self.webhook_url!r}")
            secret = "" if self.webhook_secret is None else self.webhook_secret.get_secret_value()
            try:
                valid = secret.startswith("whsec_") and len(
                    base64.b64decode(secret[6:], validate=True)) >= 16
            except ValueError:
                valid = False
            if not valid:
                raise ValueError(
                    "LOOPWATCH_WEBHOOK_URL needs LOOPWATCH_WEBHOOK_SECRET: whsec_ and the "
                    "base64 of at least 16 random bytes (the receiver checks the signature "
                    "with it)")
        if self.smtp_host is not None and not self.email_to:
            raise ValueError("LOOPWATCH_SMTP_HOST needs LOOPWATCH_EMAIL_TO (the recipients)")
        return self

    @model_validator(mode="after")
    def _no_unsafe_defaults(self) -> Settings:
        if self.environment != "development":
            self._refuse_default_secrets()
        if self.buffer_horizon_s < self.window_s:
            raise ValueError("LOOPWATCH_BUFFER_HORIZON_S must be at least LOOPWATCH_WINDOW_S")
        return self

    def _refuse_default_secrets(self) -> None:
        key = None if self.api_key is None else self.api_key.get_secret_value()
        if key is None or key.strip().lower() in KNOWN_DEFAULT_SECRETS \
                or len(key.strip()) < 16 or key != key.strip():
            raise ValueError(
                f"LOOPWATCH_API_KEY must be set to a secret of at least 16 characters, "
                f"without leading or trailing blanks, in {self.environment}"
            )
        if self.database_url is not None:
            try:
                url = make_url(self.database_url.get_secret_value())
            except ArgumentError:
                raise ValueError("LOOPWATCH_DATABASE_URL is not a database URL") from None
            if url.password is not None and (
                url.password.lower() in KNOWN_DEFAULT_SECRETS or url.password == url.username
            ):
                raise ValueError(
                    f"LOOPWATCH_DATABASE_URL has a default password for user {url.username!r}; "
                    f"set a real one in {self.environment}"
                )
        if "*" in self.cors_origins:
            raise ValueError(
                f"LOOPWATCH_CORS_ORIGINS may not be '*' in {self.environment}: "
                "list the origins of the pages that call the API"
            )

    @property
    def resolved_database_url(self) -> str:
        """The database URL, defaulting to ``sqlite:///<data_dir>/loopwatch.db``."""
        if self.database_url is not None:
            return self.database_url.get_secret_value()
        return f"sqlite:///{self.data_dir / 'loopwatch.db'}"

    def bootstrap_key(self) -> tuple[str, bool]:
        """The admin key and whether it was generated for this run."""
        if self.api_key is not None and self.api_key.get_secret_value():
            return self.api_key.get_secret_value(), False
        return secrets.token_urlsafe(24), True

    # Scale-out (issue 11): process roles, analysis executor, ingest shards, leadership.
    role: Literal["api", "ingest", "scheduler", "all"] = Field(
        default="all", description="what this process runs (``loopwatch serve --role``)"
    )
    executor: Literal["process", "dask"] = Field(
        default="process", description="analysis workers: local process pool or a Dask cluster"
    )
    dask_scheduler: str | None = Field(
        default=None, description="address of the Dask scheduler, e.g. tcp://dask:8786"
    )
    dask_connect_timeout_s: float = Field(
        default=30.0, gt=0,
        description="how long the start waits for the Dask scheduler before it gives up, s",
    )
    ingest_shard: int = Field(
        default=0, ge=0, description="index of this ingest process, 0 .. ingest_shards - 1"
    )
    ingest_shards: int = Field(
        default=1, ge=1, description="number of ingest processes sharing the connectors"
    )
    leader_lease_s: float = Field(
        default=15.0, gt=0,
        description="a scheduler silent this long is replaced by a standby, s",
    )

    @model_validator(mode="after")
    def _scale_out_consistent(self) -> Settings:
        if self.executor == "dask" and not self.dask_scheduler:
            raise ValueError(
                "LOOPWATCH_EXECUTOR=dask needs LOOPWATCH_DASK_SCHEDULER (e.g. tcp://dask:8786)"
            )
        if self.ingest_shard >= self.ingest_shards:
            raise ValueError(
                f"LOOPWATCH_INGEST_SHARD ({self.ingest_shard}) must be below "
                f"LOOPWATCH_INGEST_SHARDS ({self.ingest_shards})"
            )
        return self
