"""Configs as dataclasses: YAML in and out, ``key.sub=value`` command-line overrides, strict checking.

A config is a (nested) dataclass with defaults and a docstring per field (``#:`` comments). Everything
that reaches a run is checked *before any work*: an unknown key or a value of the wrong type raises one
``ToolkitError`` naming the key (with a suggestion for typos) and the expected type.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, Callable, TypeVar

import yaml

from toolkit.errors import ToolkitError
from toolkit.io import atomic_write_text, check_readable_file

T = TypeVar("T")


def to_dict(cfg: Any, skip: Callable[[Any, dataclasses.Field], bool] | None = None) -> dict[str, Any]:
    """Dataclass (or any nesting of them in tuples, lists, dicts) -> plain YAML-safe values (tuples become lists);
    ``skip(dataclass instance, field)`` true leaves that field out."""

    def conv(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v) if not (skip and skip(v, f))}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        return v

    return conv(cfg)


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


_EXPONENT_ONLY = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Check ``value`` against the annotation ``tp`` (after YAML parsing); ints are accepted as floats."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, key)
            except ToolkitError as e:
                errors.append(str(e))
        raise ToolkitError(f"config key '{key}': expected {_type_name(tp)}, got {value!r}")
    if origin is typing.Literal:
        if value not in args:
            raise ToolkitError(f"config key '{key}': expected one of {list(args)}, got {value!r}")
        return value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ToolkitError(f"config key '{key}': expected a list, got {value!r}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ToolkitError(f"config key '{key}': expected {len(args)} values, got {len(value)}")
            return tuple(_coerce(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
        inner = args[0] if args else Any
        out = [_coerce(v, inner, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(out) if origin is tuple else out
    if origin is dict:
        if not isinstance(value, dict):
            raise ToolkitError(f"config key '{key}': expected a mapping, got {value!r}")
        return dict(value)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ToolkitError(f"config key '{key}': expected a mapping of {tp.__name__} fields, got {value!r}")
        return from_dict(tp, value, prefix=key + ".")
    if tp is bool:
        if not isinstance(value, bool):
            raise ToolkitError(f"config key '{key}': expected true/false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ToolkitError(f"config key '{key}': expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, str) and _EXPONENT_ONLY.fullmatch(value.strip()):
            value = float(value)  # PyYAML (YAML 1.1) reads "4e-3", with no dot, as a string
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ToolkitError(f"config key '{key}': expected a number, got {value!r}")
        if not math.isfinite(value):  # YAML reads .nan / .inf as floats; no setting means either
            raise ToolkitError(f"config key '{key}': expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ToolkitError(f"config key '{key}': expected a string, got {value!r}")
        return value
    if isinstance(tp, type) and not isinstance(value, tp):
        raise ToolkitError(f"config key '{key}': expected {_type_name(tp)}, got {value!r}")
    return value


def _unknown(key: str, known: list[str]) -> ToolkitError:
    close = difflib.get_close_matches(key.rsplit(".", 1)[-1], known, n=1)
    hint = f"; did you mean '{close[0]}'?" if close else f"; known keys: {', '.join(known)}"
    return ToolkitError(f"unknown config key '{key}'{hint}")


def from_dict(cls: type[T], data: dict[str, Any], prefix: str = "") -> T:
    """Build dataclass ``cls`` from a (partial) dict; missing keys keep their defaults."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for k, v in data.items():
        if k not in fields:
            raise _unknown(prefix + k, sorted(fields))
        kwargs[k] = _coerce(v, hints[k], prefix + k)
    return cls(**kwargs)


_YAML11_NUMBER = re.compile(r"[-+]?(0[0-7_]+|[0-9][0-9_]*(:[0-5]?[0-9])+(\.[0-9_]*)?)")
"""Numbers YAML 1.1 (PyYAML) reads in base 8 (a leading 0) or base 60 (colons)."""


def _merged(base: dict, new: dict) -> dict:
    """``base`` with ``new``'s keys, nested mappings merged key by key."""
    out = dict(base)
    for k, v in new.items():
        out[k] = _merged(out[k], v) if isinstance(out.get(k), dict) and isinstance(v, dict) else v
    return out


def apply_overrides(cfg: T, overrides: list[str]) -> T:
    """Apply ``["a.b=1", "c=[1, 2]"]`` (values parsed as YAML) to a config; returns a new config."""
    data = to_dict(cfg)
    for item in overrides:
        if "=" not in item:
            raise ToolkitError(f"override {item!r}: expected KEY=VALUE (e.g. train.steps=100)")
        key, raw = item.split("=", 1)
        key = key.strip().removeprefix("--")
        r = raw.strip()
        if _YAML11_NUMBER.fullmatch(r) and (":" in r or int(r.replace("_", "")) != yaml.safe_load(r)):
            # YAML 1.1 reads 010 as 8 and 1:30 as 90, silently
            raise ToolkitError(f"override {item!r}: {r!r} would read as a base-8 or base-60 number "
                               f"({yaml.safe_load(r)}); write the number without leading zeros or colons")
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError:
            value = raw
        node, cls = data, type(cfg)
        parts = key.split(".")
        for i, p in enumerate(parts):
            names = [f.name for f in dataclasses.fields(cls)]
            if p not in names:
                raise _unknown(".".join(parts[: i + 1]), names)
            if i == len(parts) - 1:
                # A section given as a mapping changes the keys it names: the others keep the preset's values.
                node[p] = _merged(node[p], value) if isinstance(node.get(p), dict) and isinstance(value, dict) else value
            else:
                cls = typing.get_type_hints(cls)[p]
                if not dataclasses.is_dataclass(cls):
                    raise ToolkitError(f"config key '{'.'.join(parts[: i + 1])}' is not a section")
                node = node[p]
    return from_dict(type(cfg), data)


def load_yaml_config(cls: type[T], path: str | Path) -> T:
    path = check_readable_file(path, "config file")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as e:
        raise ToolkitError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ToolkitError(f"{path}: expected a mapping at the top level")
    try:
        return from_dict(cls, data)
    except ToolkitError as e:
        raise ToolkitError(f"{path}: {e}") from None


def save_yaml_config(cfg: Any, path: str | Path) -> None:
    atomic_write_text(path, yaml.safe_dump(to_dict(cfg), sort_keys=False))


NEUTRAL = {"neutral": True}
"""Field metadata (``dataclasses.field(default=..., metadata=NEUTRAL)``) of an option added with a default that
keeps the behaviour from before it existed: :func:`config_hash` leaves it out while it holds that default, so
the stages of runs made before it was added stay up to date."""


def _default(f: dataclasses.Field) -> Any:
    return f.default_factory() if f.default is dataclasses.MISSING else f.default  # type: ignore[misc]


def _neutral_at_default(obj: Any, f: dataclasses.Field) -> bool:
    return bool(f.metadata.get("neutral")) and getattr(obj, f.name) == _default(f)


def config_hash(obj: Any) -> str:
    """A stable short hash of a config (or any YAML-able value), for stage skipping (:data:`NEUTRAL` fields at
    their defaults left out)."""
    import hashlib

    data = to_dict(obj, skip=_neutral_at_default)
    return hashlib.sha256(yaml.safe_dump(data, sort_keys=True).encode()).hexdigest()[:16]
