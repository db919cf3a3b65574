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
    if isinstance(view_space, dict) and view_space.get("source") not in (None, "builtin", "generated"):
        view_space["source"] = _config_file(path, "view_space.source", view_space["source"], "'builtin', 'generated'")
    if data.get("poco_weights") not in (None, "builtin"):
        data["poco_weights"] = _config_file(path, "poco_weights", data["poco_weights"], "'builtin'")
    return config_from_dict(data, origin=str(path))


def _config_file(config_path: Path, field: str, value: object, keywords: str) -> str:
    """A file a config names, resolved against the config's folder (it enters the hash by content)."""
    resolved = (config_path.parent / str(value)).resolve()
    if not resolved.is_file():
        raise ConfigError(
            f"{config_path}: {field} = {value!r} is neither {keywords} nor an existing file (looked for {resolved})"
        )
    return str(resolved)


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
