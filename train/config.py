"""Configs as dataclasses: YAML in and out, ``key.sub=value`` command-line overrides, strict checking.

A config is a (nested) dataclass with defaults and a docstring per field. Each field declares its range in its
metadata (``field(default=300, metadata=at_least(1, "a count"))``), read by one checker, :func:`check_fields`,
at load and override time; rules across fields live in ``train.stages.checks``. Every failure is one
``ToolkitError`` naming the key (with a suggestion for typos) and the expected value.

Field metadata rather than pydantic models: the configs stay plain dataclasses like the component configs
they set (``dataclasses.replace``, the fingerprints' YAML), the messages keep their wording, no new dependency.
"""

from __future__ import annotations

import contextlib
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
from toolkit.safe_yaml import YAMLSyntaxError, load_yaml, load_yaml_file

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


# ----------------------------------------------------------------------------- field metadata
class Checks(dict):
    """A config field's metadata: ``rules`` (``(ok, expected)`` pairs, checked in order: ``ok(value)`` true, else
    the error reads "expected {expected}, got {value}"), ``neutral``, ``maps_to``; ``a | b`` keeps both's rules."""

    def __or__(self, other: dict) -> "Checks":
        return Checks({**self, **other, "rules": (*self.get("rules", ()), *other.get("rules", ()))})


def rule(ok: Callable[[Any], bool], expected: str) -> Checks:
    return Checks(rules=((ok, expected),))


def at_least(low: float, what: str = "a value") -> Checks:
    """``value >= low``: "a count >= 1" for ``what`` "a count" (a ``{}`` in ``what`` places the bound)."""
    return rule(lambda v: v >= low, what.format(f">= {low}") if "{}" in what else f"{what} >= {low}")


def within(low: float, high: float, what: str = "a value", *, low_open: bool = False,
           high_open: bool = False) -> Checks:
    """``low <= value <= high``, either end open: "a learning rate in (0, 1]"."""
    bound = f"in {'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
    return rule(lambda v: (low < v if low_open else low <= v) and (v < high if high_open else v <= high),
                what.format(bound) if "{}" in what else f"{what} {bound}")


NEUTRAL = Checks(neutral=True)
"""Field metadata of an option added with a default that keeps the behaviour from before it existed:
:func:`config_hash` leaves it out while it holds that default, so the stages of runs made before it was added
stay up to date."""


def maps_to(component: str, name: str) -> Checks:
    """Field metadata: this stage field sets field ``name`` of the component config class named ``component``
    (see :func:`component`)."""
    return Checks(maps_to=(component, name))


def _mapping(cls: type, section: Any) -> dict[str, str]:
    """{component field: stage field} for the fields of ``section`` that map to the component config ``cls``."""
    return {f.metadata["maps_to"][1]: f.name for f in dataclasses.fields(section)
            if f.metadata.get("maps_to", ("",))[0] == cls.__name__}


def component(base: Any, section: Any, **stage_set: Any) -> Any:
    """The component config ``base`` (a dataclass, or an instance of one to update) with every field that a field
    of ``section`` maps to (:func:`maps_to`) set from ``section``, and ``stage_set``; the others as in ``base``."""
    cls, base = (base, base()) if isinstance(base, type) else (type(base), base)
    mapped = {name: getattr(section, stage_field) for name, stage_field in _mapping(cls, section).items()}
    return dataclasses.replace(base, **mapped, **stage_set)


def check_component(cls: type, section: Any, prefix: str) -> None:
    """Run the ``validate()`` of component config ``cls`` on what ``section`` sets, so that its rules are stated
    once, there; its errors name the config key (``prefix`` + the stage field) instead of the component field:
    "Cls.name: ..." (a rule on one field) becomes "config key 'prefix.field': ...", and "Cls: name and name ..."
    (a rule across fields) "config keys 'prefix.field' and 'prefix.field' ..."."""
    try:
        component(cls, section).validate()
    except ToolkitError as err:
        text, keys = str(err), {name: prefix + field for name, field in _mapping(cls, section).items()}
        for name, key in keys.items():
            text = text.replace(f"{cls.__name__}.{name}:", f"config key '{key}':")
        if text.startswith(f"{cls.__name__}: ") and keys:
            names = re.compile(r"\b(" + "|".join(map(re.escape, keys)) + r")\b")
            text = "config keys " + names.sub(lambda m: f"'{keys[m[1]]}'", text[len(cls.__name__) + 2:])
        raise ToolkitError(text) from None


# ----------------------------------------------------------------------------- checking
def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


_EXPONENT_ONLY = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")
_EXPECTED = {bool: "true/false", int: "an integer", float: "a number", str: "a string", dict: "a mapping",
             list: "a list", tuple: "a list"}


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """``value`` checked against the annotation ``tp`` (after YAML parsing); ints pass as floats, bools as
    neither; a nested section is read with :func:`from_dict`."""
    origin, args = typing.get_origin(tp) or tp, typing.get_args(tp)
    fail = lambda what: ToolkitError(f"config key '{key}': expected {what}, got {value!r}")  # noqa: E731
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        for a in (a for a in args if a is not type(None)):
            with contextlib.suppress(ToolkitError):
                return _coerce(value, a, key)
        raise fail(_type_name(tp))
    if origin is typing.Literal and value not in args:
        raise fail(f"one of {list(args)}")
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, (dict, tp)):
            raise fail(f"a mapping of {tp.__name__} fields")
        return check_fields(value, key + ".") if isinstance(value, tp) else from_dict(tp, value, prefix=key + ".")
    if tp is float and isinstance(value, str) and _EXPONENT_ONLY.fullmatch(value.strip()):
        value = float(value)  # PyYAML (YAML 1.1) reads "4e-3", with no dot, as a string
    accepted = {list: (list, tuple), tuple: (list, tuple), float: (int, float)}.get(origin, origin)
    if isinstance(accepted, (type, tuple)) and (not isinstance(value, accepted)
                                               or isinstance(value, bool) and tp in (int, float)):
        raise fail(_EXPECTED.get(origin, _type_name(tp)))
    if tp is float and not math.isfinite(value):  # YAML reads .nan / .inf as floats; no setting means either
        raise fail("a finite number")
    if origin in (list, tuple):
        fixed = origin is tuple and args and args[-1] is not Ellipsis
        if fixed and len(value) != len(args):
            raise ToolkitError(f"config key '{key}': expected {len(args)} values, got {len(value)}")
        items = [_coerce(v, args[i] if fixed else args[0] if args else Any, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    return float(value) if tp is float else value


def check_fields(cfg: T, prefix: str = "", spell: Callable[[str], str] = str) -> T:
    """``cfg``, a dataclass, once every field (its sections' too) passes its type and its declared rules; an error
    names the field as ``prefix + spell(name)`` (a command line's flag: ``spell`` turns ``_`` into ``-``)."""
    hints = typing.get_type_hints(type(cfg))
    for f in dataclasses.fields(cfg):
        key, value = prefix + spell(f.name), getattr(cfg, f.name)
        _coerce(value, hints[f.name], key)
        for ok, expected in f.metadata.get("rules", ()):
            if not ok(value):
                raise ToolkitError(f"config key '{key}': expected {expected}, got {value!r}")
    return cfg


def _unknown(key: str, known: list[str]) -> ToolkitError:
    close = difflib.get_close_matches(key.rsplit(".", 1)[-1], known, n=1)
    hint = f"; did you mean '{close[0]}'?" if close else f"; known keys: {', '.join(known)}"
    return ToolkitError(f"unknown config key '{key}'{hint}")


def from_dict(cls: type[T], data: dict[str, Any], prefix: str = "") -> T:
    """Build dataclass ``cls`` from a (partial) dict, checked (:func:`check_fields`); missing keys keep their
    defaults."""
    hints, names = typing.get_type_hints(cls), sorted(f.name for f in dataclasses.fields(cls))
    if unknown := [k for k in data if k not in names]:
        raise _unknown(prefix + unknown[0], names)
    return check_fields(cls(**{k: _coerce(v, hints[k], prefix + k) for k, v in data.items()}), prefix)


# ----------------------------------------------------------------------------- overrides, files, hashes


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
        try:
            value = load_yaml(raw, f"override {item!r}") if raw.strip() else ""
        except YAMLSyntaxError:
            value = raw  # not YAML: the text itself (a path with a colon, say)
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
    data = load_yaml_file(path) or {}
    if not isinstance(data, dict):
        raise ToolkitError(f"{path}: expected a mapping at the top level")
    try:
        return from_dict(cls, data)
    except ToolkitError as e:
        raise ToolkitError(f"{path}: {e}") from None


def save_yaml_config(cfg: Any, path: str | Path) -> None:
    atomic_write_text(path, yaml.safe_dump(to_dict(cfg), sort_keys=False))



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
