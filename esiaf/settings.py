"""Settings: defaults < YAML file < environment variables.

Every service describes its settings as a pydantic model. :func:`load_settings`
builds it from the model's defaults, then an optional YAML file, then the
environment. Unknown keys are an error, in the YAML file and in the
environment alike, so a typo never silently falls back to a default.

Environment variables are named ``ESIAF_<SERVICE>_<FIELD>`` (upper case), e.g.
``ESIAF_VAD_MAX_MS=6000``. Fields that every component has (those of
:class:`ComponentSettings`) may also be given for all services at once as
``ESIAF_<FIELD>``, e.g. ``ESIAF_ORCHESTRATOR_URL``; the service-specific name
wins. Values from the environment are parsed as YAML scalars or flow
collections, so ``ESIAF_ASR_N_BEST=3`` and ``ESIAF_X_LIST=[a, b]`` work.

A service with several backends keeps each backend's own settings in a nested model named as the
backend (:class:`BackendSettings`): ``backend: energy`` reads ``energy: {db_min: 70}`` in YAML,
``ESIAF_VAD_ENERGY__DB_MIN=70`` in the environment (two underscores between the levels) and
``--set energy.db_min=70`` on a command line; settings of a backend that is not chosen are an error.
"""
from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from esiaf import auth, keys
from esiaf.transport import AUDIO_HWM

ENV_PREFIX = "ESIAF_"
log = logging.getLogger(__name__)

S = TypeVar("S", bound=BaseModel)


class SettingsError(Exception):
    """Bad configuration: the message says which key and source are wrong."""


class StrictModel(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)  # no nan, no inf
    # old spellings of settings -> their names now: accepted (YAML, environment, --set) for one
    # release, with one deprecation line each
    renamed: ClassVar[dict[str, str]] = {}

    @model_validator(mode="before")
    @classmethod
    def _old_spellings(cls, data: Any) -> Any:
        if not cls.renamed or not isinstance(data, dict) or not data.keys() & cls.renamed.keys():
            return data
        data = dict(data)
        for old, new in cls.renamed.items():
            if old not in data:
                continue
            value = data.pop(old)
            *parents, leaf = new.split(".")  # "energy.db_min": a backend's nested setting
            where = data
            for parent in parents:
                inner = where.get(parent)
                inner = inner.model_dump(exclude_unset=True) if isinstance(inner, BaseModel) else dict(inner or {})
                where[parent] = inner
                where = inner
            log.warning("setting %s is deprecated and goes in the next release: it is now %s%s", old, new,
                        f" (both given: {new}={where[leaf]!r} wins)" if leaf in where else "")
            where.setdefault(leaf, value)
        return data


class ComponentSettings(StrictModel):
    """What every component has, whatever it does."""

    name: str = ""  # the component's name; defaults to the service's name
    # this instance's id, unique among the live ones; default: the name and a random suffix. Several
    # instances of one name share the streams (the orchestrator assigns each to one of them)
    instance: str = Field(default="", pattern=r"^$|^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")
    orchestrator_url: str = "http://127.0.0.1:8000"
    stream_id: str = "default"
    bind_host: str = "127.0.0.1"  # where this component's audio output socket binds
    advertise_host: str = ""  # how others reach it; defaults to bind_host (or the hostname if 0.0.0.0)
    audio_port: int = 0  # 0 = any free port
    register_timeout_s: float = 30.0  # keep retrying the orchestrator this long at start-up
    # audio messages queued per connection, each way (ZeroMQ SNDHWM and RCVHWM): live audio past it is
    # dropped and counted, a replay's waits (docs/protocol.md, "Flow control"); `esiaf run --fast` makes it small
    audio_queue: int = Field(default=AUDIO_HWM, ge=1)
    # streams whose state a component keeps (esiaf/per_stream.py): past it the least recently heard
    # one's is forgotten (a stream whose source died, or a peer naming a new stream per message)
    max_streams: int = Field(default=256, ge=1)
    log_level: str = "INFO"
    health_file: str = ""  # touched whenever the orchestrator answers (see esiaf.tools.health)
    # tests only: this component's clock runs this far ahead of the host's (capture times, heartbeats),
    # as another host's might
    clock_skew_s: float = 0.0

    @field_validator("log_level")
    @classmethod
    def _known_level(cls, value: str) -> str:
        if not isinstance(logging.getLevelName(value.upper()), int):
            raise ValueError(f"unknown log level {value!r}; one of DEBUG, INFO, WARNING, ERROR, CRITICAL")
        return value.upper()


class BackendSettings(ComponentSettings):
    """A component with several backends: ``backend`` names one, and each backend's own settings are
    a nested model in the field of the same name (``backends`` lists those fields). The settings of
    a backend that is not the chosen one are refused (:meth:`unused_backend_settings`)."""

    backends: ClassVar[tuple[str, ...]] = ()
    backend: str

    @field_validator("backend")
    @classmethod
    def _known_backend(cls, value: str) -> str:
        if value not in cls.backends:
            raise ValueError(f"unknown backend {value!r}; one of {', '.join(cls.backends)}")
        return value

    def unused_backend_settings(self) -> list[str]:
        """``section.field`` of every setting given for a backend other than ``backend``."""
        return [f"{name}.{field}" for name in self.backends if name != self.backend
                for field in sorted(getattr(self, name).model_fields_set)]


def sections(model: type[BaseModel]) -> dict[str, type[BaseModel]]:
    """The fields of ``model`` that are settings models of their own (a backend's), by name."""
    return {name: field.annotation for name, field in model.model_fields.items()
            if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel)}


def nest(key: str, value: Any, into: dict[str, Any], separator: str = ".") -> None:
    """``into[a][b] = value`` for the key ``a.b`` (``a__b`` with ``separator="__"``)."""
    *parents, leaf = key.split(separator)
    for parent in parents:
        into = into.setdefault(parent, {}) if isinstance(into.get(parent, {}), dict) else into
    into[leaf] = value


def merged(base: dict[str, Any], more: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` updated with ``more``, nested mappings merged key by key (a backend's settings from a
    file and one of them from the environment)."""
    out = dict(base)
    for key, value in more.items():
        out[key] = merged(out[key], value) if isinstance(value, Mapping) and isinstance(out.get(key), dict) \
            else value
    return out


def parse_value(raw: str) -> Any:
    """A value given as text (environment, --set): a YAML scalar or flow collection, else the text."""
    try:
        return yaml.safe_load(raw) if raw.strip() else raw
    except yaml.YAMLError:
        return raw


def _from_env(model: type[BaseModel], service: str, env: Mapping[str, str]) -> dict[str, Any]:
    """The settings the environment gives: ``ESIAF_<FIELD>`` for the common ones, overridden by
    ``ESIAF_<SERVICE>_<FIELD>``; an unknown ``ESIAF_<SERVICE>_...`` is an error."""
    return {**_common_from_env(model, env), **_service_from_env(model, service, env)}


def _common_from_env(model: type[BaseModel], env: Mapping[str, str]) -> dict[str, Any]:
    """``ESIAF_<FIELD>`` for the fields every component has (those ``model`` has too)."""
    common = set(ComponentSettings.model_fields) & set(model.model_fields)
    values: dict[str, Any] = {}
    for key, raw in env.items():
        if key.startswith(ENV_PREFIX) and key[len(ENV_PREFIX):].lower() in common:
            values.setdefault(key[len(ENV_PREFIX):].lower(), parse_value(raw))
    return values


def _service_from_env(model: type[BaseModel], service: str, env: Mapping[str, str]) -> dict[str, Any]:
    """``ESIAF_<SERVICE>_<FIELD>``; SettingsError for a field ``model`` does not have."""
    nested = sections(model)
    current = set(model.model_fields) - set(nested) | {
        f"{name}__{field}" for name, inner in nested.items() for field in inner.model_fields}
    fields = current | set(getattr(model, "renamed", {}))  # old spellings too, said to be deprecated
    service_prefix = f"{ENV_PREFIX}{service.upper()}_"
    values: dict[str, Any] = {}
    for key, raw in env.items():
        if not key.startswith(service_prefix):
            continue
        field = key[len(service_prefix):].lower()
        if field == "config" or key[len(ENV_PREFIX):].lower() in ComponentSettings.model_fields:
            continue  # ESIAF_ORCHESTRATOR_URL is every component's, not the orchestrator's "url"
        if field not in fields:
            raise SettingsError(
                f"unknown setting {key} for {service}; known: "
                + ", ".join(sorted(service_prefix + f.upper() for f in current)))
        nest(field, parse_value(raw), values, separator="__")
    return values


# "1": this process is a spare (esiaf/tools/launcher.py): imported and its settings read, it waits for a
# line on stdin before it registers and runs (esiaf/runner.py), or ends at its end
STANDBY_ENV = "ESIAF_STANDBY"
# ESIAF_* variables that name no service: read by the SDK, the tools or compose.yaml
GLOBAL_VARIABLES = {auth.TOKEN_ENV, auth.TOKEN_FILE_ENV, auth.TLS_CA_ENV, keys.CURVE_DIR_ENV, keys.CURVE_KEY_ENV,
                    STANDBY_ENV} | {
    ENV_PREFIX + name for name in ("SHARED_DATA", "TAG", "BASE_TAG", "REBUILD_BASE", "HTTP_BIND", "HTTP_PORT",
                                   "INPUT_FILE", "INPUT_DIR", "SERVICE")}


def unknown_variables(env: Mapping[str, str], services: Iterable[str]) -> list[str]:
    """The ``ESIAF_*`` variables of ``env`` that name none of ``services`` (``ESIAF_<SERVICE>_...``),
    no setting every component has and no global one: a typo (``ESIAF_VDA_DB_MIN``), reported
    rather than silently ignored."""
    prefixes = tuple(f"{ENV_PREFIX}{service.upper()}_" for service in services)
    known = GLOBAL_VARIABLES | {ENV_PREFIX + field.upper() for field in ComponentSettings.model_fields}
    return sorted(key for key in env if key.startswith(ENV_PREFIX) and key not in known
                  and not key.startswith(prefixes))


def read_yaml_file(path: Path) -> dict[str, Any]:
    """A YAML file holding a mapping; SettingsError (one clear line) otherwise."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise SettingsError(f"cannot read config file {path}: {exc.strerror}") from None
    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise SettingsError(f"config file {path} is not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise SettingsError(f"config file {path} must hold a mapping of settings, not {type(data).__name__}")
    return data


def load_settings(model: type[S], service: str, /, *, config: str | Path | None = None,
                  env: Mapping[str, str] | None = None, check_backend: bool = True, **overrides: Any) -> S:
    """Builds ``model`` from defaults < YAML < environment < ``overrides``.

    ``config`` (or ``ESIAF_<SERVICE>_CONFIG``) names the YAML file. ``overrides``
    are values given on a command line; ``None`` values are ignored. ``check_backend=False``: settings
    of another backend than the chosen one are let through (whoever starts the service may still
    choose its backend).
    """
    env = os.environ if env is None else env
    config = config or env.get(f"{ENV_PREFIX}{service.upper()}_CONFIG")
    given = [(f"config file {config}", read_yaml_file(Path(config)) if config else {}),
             ("environment", _from_env(model, service, env)),
             ("command line", {k: v for k, v in overrides.items() if v is not None})]
    values: dict[str, Any] = {}
    origin: dict[str, str] = {}  # where each value came from, the last source that gave it
    for source, given_values in given:
        values = merged(values, given_values)
        renamed: dict[str, str] = getattr(model, "renamed", {})  # an old spelling blames its source too
        origin.update({key: source for given_key in given_values
                       for key in (given_key, renamed.get(given_key, given_key).split(".")[0])})
    try:
        settings = model(**values)
    except ValidationError as exc:
        raise _settings_error(exc, service, origin, given) from None
    if check_backend and isinstance(settings, BackendSettings) and settings.unused_backend_settings():
        unused = settings.unused_backend_settings()
        blamed = sorted({origin.get(key.split(".")[0], "defaults") for key in unused})
        raise SettingsError(f"bad {service} settings (from {' and '.join(blamed)}): {', '.join(unused)} "
                            f"{'is' if len(unused) == 1 else 'are'} for another backend than {settings.backend!r} "
                            f"(set backend, or leave {'it' if len(unused) == 1 else 'them'} out)")
    if isinstance(settings, ComponentSettings) and not settings.name:
        settings.name = service
    return settings


def _settings_error(exc: ValidationError, service: str, origin: Mapping[str, str],
                    given: list[tuple[str, dict[str, Any]]]) -> SettingsError:
    """One line: every problem pydantic found, and the sources to blame for them."""
    problems: list[str] = []
    blamed: list[str] = []
    for err in exc.errors():
        key = str(err["loc"][0]) if err["loc"] else ""
        if key in origin:  # a bad value: the source it came from
            sources = [origin[key]]
        elif key:  # a value missing (or a default that does not fit)
            sources = ["defaults"]
        else:  # a check across values: every source that gave some
            sources = [source for source, given_values in given if given_values]
        blamed.extend(s for s in sources if s not in blamed)
        problems.append(f"{'.'.join(str(p) for p in err['loc']) or '(root)'}: {err['msg']}")
    where = " and ".join(blamed) or "defaults"
    return SettingsError(f"bad {service} settings (from {where}): {'; '.join(problems)}")
