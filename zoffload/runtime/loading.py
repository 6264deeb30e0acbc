"""Loading settings: defaults, then a YAML file, then ``ZOFFLOAD_*`` environment variables,
then command-line flags; unknown keys are errors. The effective config is written beside results.

Environment variables address nested keys with ``__``: ``ZOFFLOAD_ROBOT__VOXEL=0.03`` or
``ZOFFLOAD_EDGE__MAPPER__MAX_POINTS_PER_VOXEL=10``. Lists, pairs and whole sections are YAML
(``ZOFFLOAD_ROBOT__ZENOH__CONNECT=[tcp/10.0.0.2:7447]``); ``null`` unsets an optional value and an
empty variable counts as unset. A variable under the prefix that names no setting is an error.
"""

from __future__ import annotations

import difflib
import functools
import os
import types
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar, Union, cast, get_args, get_origin

import yaml
from pydantic import BaseModel, ValidationError
from pydantic.fields import FieldInfo
from pydantic_settings import BaseSettings, EnvSettingsSource, SettingsError
from pydantic_settings.sources.utils import parse_env_vars

from zoffload.runtime.errors import ConfigError

S = TypeVar("S", bound=BaseModel)

# The daemons' environment prefixes: ZOFFLOAD_ROBOT__VOXEL=0.03, ZOFFLOAD_EDGE__MAPPER__QUEUE=4
ROBOT_ENV = "ZOFFLOAD_ROBOT__"
EDGE_ENV = "ZOFFLOAD_EDGE__"


def unwrap_optional(annotation: Any) -> Any:
    """``X | None`` → ``X``; any other annotation unchanged."""
    if get_origin(annotation) in (Union, types.UnionType):
        members = [a for a in get_args(annotation) if a is not type(None)]
        if len(members) == 1:
            return members[0]
    return annotation


def section_model(field: FieldInfo) -> type[BaseModel] | None:
    """The settings model a field holds (``perception``, ``zenoh``...), None for a plain value."""
    annotation = unwrap_optional(field.annotation)
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    return None


def _deep_merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out


class _EnvironmentSource(EnvSettingsSource):
    """pydantic-settings' environment source reading a given mapping (tests pass their own), with
    complex values (lists, pairs, sections) in YAML rather than JSON so that
    ``[tcp/127.0.0.1:7447]`` needs no quoting; scalars stay strings for pydantic to parse."""

    def __init__(self, settings_cls: type[BaseSettings], prefix: str, environ: Mapping[str, str]) -> None:
        self._environ = environ  # read by _load_env_vars, which the base __init__ calls
        super().__init__(settings_cls, case_sensitive=False, env_prefix=prefix, env_nested_delimiter="__",
                         env_ignore_empty=True, env_parse_none_str="null")

    def _load_env_vars(self) -> Mapping[str, str | None]:
        # The hook pydantic-settings' own dotenv source overrides to read somewhere else.
        return parse_env_vars(self._environ, self.case_sensitive, self.env_ignore_empty,
                              self.env_parse_none_str)

    def decode_complex_value(self, field_name: str, field: FieldInfo, value: Any) -> Any:
        try:
            return yaml.safe_load(value)
        except yaml.YAMLError as exc:
            # ConfigError, not ValueError: pydantic-settings would rewrap a ValueError in a message
            # naming its own classes; this one names the variable.
            name = next((n for n, v in self._environ.items() if v == value
                         and n.lower().startswith(self.env_prefix.lower())
                         and n.lower().endswith(field_name.lower())), f"{self.env_prefix}...{field_name}")
            problem = getattr(exc, "problem", None) or exc
            raise ConfigError(f"environment variable {name}: {value!r} is not valid YAML: {problem}") from exc


@functools.cache
def _settings_class(cls: type[BaseModel]) -> type[BaseSettings]:
    """``cls`` with BaseSettings mixed in, as pydantic-settings' sources expect. The models stay
    plain BaseModels so that building one in Python (tests, the demo) never reads the environment."""
    mixed = type(cls.__name__, (BaseSettings, cls), {"__module__": cls.__module__, "__doc__": cls.__doc__})
    return cast("type[BaseSettings]", mixed)


def _near(model: type[BaseModel], key: str) -> str:
    """`` (did you mean 'x'?)`` for a key close to one of ``model``'s settings, else ``""``."""
    close = difflib.get_close_matches(key.lower(), list(model.model_fields), n=1, cutoff=0.6)
    if not close and key and (prefixed := [f for f in model.model_fields if f.startswith(key.lower())]):
        close = prefixed[:1]  # a flag's short spelling used as a key: rate -> rate_hz
    return f" (did you mean {close[0]!r}?)" if close else ""


def _no_such_setting(cls: type[BaseModel], loc: tuple[Any, ...]) -> str:
    """The message for an unknown key at ``loc``: what the section has close to it."""
    model: type[BaseModel] | None = cls
    for key in loc[:-1]:
        field = model.model_fields.get(str(key)) if model is not None else None
        model = section_model(field) if field is not None else None
    hint = _near(model, str(loc[-1])) if model is not None else ""
    return f"no such setting{hint}"


def _check_variable_names(cls: type[BaseModel], prefix: str, environ: Mapping[str, str]) -> None:
    """A variable under the prefix must name a setting: pydantic-settings skips the others, and a
    typo silently ignored is a classic field bug."""
    single = prefix.rstrip("_") + "_"  # ZOFFLOAD_ROBOT_VOXEL: one underscore short of the prefix
    for name in environ:
        if name.upper().startswith(single.upper()) and not name.upper().startswith(prefix.upper()):
            raise ConfigError(f"environment variable {name}: settings take {prefix}KEY (two underscores"
                              f" after {single.rstrip('_')}), e.g. {prefix}{name[len(single):].upper()}")
        if not name.upper().startswith(prefix.upper()):
            continue
        keys = name[len(prefix):].lower().split("__")
        model: type[BaseModel] | None = cls
        for depth, key in enumerate(keys):
            if model is None:
                raise ConfigError(f"environment variable {name}: {'.'.join(keys[:depth])} is a value, "
                                  "not a section")
            field = model.model_fields.get(key)
            if field is None:
                path = ".".join(keys[: depth + 1])
                raise ConfigError(f"environment variable {name}: {cls.__name__} has no setting {path!r}"
                                  f"{_near(model, key)}")
            model = section_model(field)


def environment_values(
    cls: type[BaseModel], prefix: str, environ: Mapping[str, str] | None = None
) -> dict[str, Any]:
    """The nested values that ``<prefix>KEY`` / ``<prefix>SECTION__KEY`` variables set, not yet validated."""
    environ = os.environ if environ is None else environ
    _check_variable_names(cls, prefix, environ)
    try:
        return _EnvironmentSource(_settings_class(cls), prefix, environ)()
    except SettingsError as exc:  # not expected from our source; kept readable all the same
        raise ConfigError(f"environment variables {prefix}*: {exc}") from exc


def _read_file(file: str | Path) -> dict[str, Any]:
    path = Path(file)
    try:
        loaded = yaml.safe_load(path.read_text()) or {}
    except OSError as exc:
        raise ConfigError(f"config file {path}: {exc.strerror}") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path}: not valid YAML: {exc}") from exc
    if not isinstance(loaded, dict):
        raise ConfigError(f"config file {path}: the top level must be a mapping")
    return loaded


def load_settings(
    cls: type[S],
    file: str | Path | None = None,
    flags: Mapping[str, Any] | None = None,
    env_prefix: str | None = None,
    environ: Mapping[str, str] | None = None,
) -> S:
    """Defaults < YAML file < environment < flags, validated; ``ConfigError`` names what is wrong.

    Only ``env_prefix`` makes it read the environment (``environ``, else ``os.environ``)."""
    data = _read_file(file) if file is not None else {}
    if env_prefix:
        data = _deep_merge(data, environment_values(cls, env_prefix, environ))
    if flags:
        data = _deep_merge(data, {k: v for k, v in flags.items() if v is not None})
    try:
        return cls.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in err['loc']) or '(top)'}: "
            f"{_no_such_setting(cls, err['loc']) if err['type'] == 'extra_forbidden' else err['msg']}"
            for err in exc.errors()
        )
        where = f" (from {file})" if file else ""
        raise ConfigError(f"invalid {cls.__name__}{where}: {problems}") from exc


def write_effective(settings: BaseModel, path: Path) -> Path:
    """Write the settings actually used, as YAML, so every result says how it was made; a folder
    that cannot be made or written is a configuration error naming it."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(yaml.safe_dump(settings.model_dump(mode="json"), sort_keys=False))
    except OSError as exc:
        raise ConfigError(f"cannot write {path} (the results folder {path.parent}): "
                          f"{exc.strerror or exc}") from exc
    return path
