"""Load a `GenerationConfig` from TOML and write it back, with one-line errors naming the field."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import tomli_w
from pydantic import ValidationError

from datagen.errors import ConfigError
from schemas.config import GenerationConfig


def load_config(path: str | Path | None = None) -> GenerationConfig:
    """The config in ``path`` (TOML), or the defaults when ``path`` is None.

    Relative file paths inside the config (a view-space file) resolve against the config's folder.
    """
    if path is None:
        return GenerationConfig()
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found; pass an existing TOML file to --config") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config file ({exc.strerror})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc}); fix the syntax at that position") from None
    view_space = data.get("view_space")
    if isinstance(view_space, dict):
        source = view_space.get("source")
        if isinstance(source, str) and source not in ("builtin", "generated"):
            resolved = (path.parent / source).resolve()
            if not resolved.is_file():
                raise ConfigError(
                    f"{path}: view_space.source = {source!r} is neither 'builtin', 'generated' nor an "
                    f"existing view-space file (looked for {resolved})"
                )
            view_space["source"] = str(resolved)
    weights = data.get("poco_weights")
    if isinstance(weights, str) and weights != "builtin":
        resolved_weights = (path.parent / weights).resolve()
        if not resolved_weights.is_file():
            raise ConfigError(
                f"{path}: poco_weights = {weights!r} is neither 'builtin' nor an existing weights file "
                f"(looked for {resolved_weights}); train one with 'datagen poco train'"
            )
        data["poco_weights"] = str(resolved_weights)
    return config_from_dict(data, origin=str(path))


def config_from_dict(data: dict[str, Any], origin: str = "config") -> GenerationConfig:
    try:
        return GenerationConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(describe_validation_error(exc, origin)) from None


def describe_validation_error(exc: ValidationError, origin: str) -> str:
    """One line per invalid field: where it is, what it is, and what is allowed."""
    problems = []
    for error in exc.errors():
        field = ".".join(str(part) for part in error["loc"]) or "(top level)"
        kind = error["type"]
        if kind == "extra_forbidden":
            allowed = _allowed_keys(error["loc"])
            problems.append(f"unknown key {field!r}; allowed keys here: {', '.join(allowed)}")
            continue
        message = error["msg"].removeprefix("Value error, ")
        value = error.get("input")
        if kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
            problems.append(f"{field} = {value!r}: {message}; allowed range: {_range_text(error['ctx'])}")
        elif isinstance(value, dict):
            problems.append(f"{field}: {message}")
        else:
            problems.append(f"{field} = {value!r}: {message}")
    return f"{origin}: invalid config: " + "; ".join(problems)


def _range_text(ctx: dict[str, Any]) -> str:
    low = f"> {ctx['gt']}" if "gt" in ctx else f">= {ctx['ge']}" if "ge" in ctx else ""
    high = f"< {ctx['lt']}" if "lt" in ctx else f"<= {ctx['le']}" if "le" in ctx else ""
    return " and ".join(part for part in (low, high) if part)


def _allowed_keys(location: tuple[Any, ...]) -> list[str]:
    model: Any = GenerationConfig
    for part in location[:-1]:
        field = model.model_fields.get(part)
        if field is None or not hasattr(field.annotation, "model_fields"):
            return []
        model = field.annotation
    return sorted(model.model_fields)


def config_to_toml(config: GenerationConfig) -> str:
    return tomli_w.dumps(config.model_dump(mode="json"))
