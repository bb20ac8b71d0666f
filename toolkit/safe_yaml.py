"""One YAML reader for every file a user hands the toolkit: bounded, unambiguous, and failing with one line.

PyYAML's ``safe_load`` executes no code, but it still accepts what no config means and what can exhaust the
machine. :func:`load_yaml` refuses, each with a one-line ``ToolkitError`` naming the source (and the line, in
a text of several):

- aliases (``*name``): a few hundred bytes of nested aliases expand to gigabytes (the "billion laughs");
- mapping keys that are not strings (``1:``, ``~:``, ``yes:`` read as an int, None, a bool);
- YAML 1.1's base-8 and base-60 numbers (``010`` reads as 8, ``1:30`` as 90) and integers of more than
  ``MAX_INT_DIGITS`` digits;
- nesting deeper than ``MAX_DEPTH`` (the composer recurses once per level);
- text that is not UTF-8, or larger than ``MAX_BYTES``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from toolkit.errors import ToolkitError

MAX_BYTES = 4 << 20
"""Largest YAML text read (a run's resolved config is ~5 KB)."""
MAX_DEPTH = 64
"""Deepest nesting of mappings and sequences (a run config nests 3 levels)."""
MAX_INT_DIGITS = 30
"""Longest integer literal (a 2**64 seed has 20 digits)."""

class YAMLSyntaxError(ToolkitError):
    """The text is not YAML at all (as opposed to YAML this reader refuses)."""


_BASE_8_OR_60 = re.compile(r"[-+]?(0[0-9_]+|[0-9][0-9_]*(:[0-5]?[0-9])+(\.[0-9_]*)?)")


def _where(loader: "_StrictLoader", node_or_mark: Any) -> str:
    """The error's source, with the line when the text has several."""
    mark = getattr(node_or_mark, "start_mark", node_or_mark)
    return f"{loader.source}, line {mark.line + 1}" if mark is not None and loader.lines > 1 else loader.source


class _StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` with the refusals of the module docstring; ``source`` names the text in errors."""

    source = "YAML"

    def __init__(self, stream: str):
        super().__init__(stream)
        self._depth = 0
        self.lines = stream.strip().count("\n") + 1

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            raise ToolkitError(f"{_where(self, self.peek_event())}: YAML aliases (*name) are not accepted")
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise ToolkitError(f"{_where(self, self.peek_event())}: nested deeper than {MAX_DEPTH} levels")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node, deep=False):
        for key_node, _ in node.value:
            if not (isinstance(key_node, yaml.ScalarNode) and key_node.tag == "tag:yaml.org,2002:str"):
                raise ToolkitError(f"{_where(self, key_node)}: a mapping key must be a string, got "
                                   f"{key_node.value!r} (quote it)")
        return super().construct_mapping(node, deep=deep)

    def construct_yaml_int(self, node):
        text = str(node.value)
        if len(text.replace("_", "").lstrip("+-")) > MAX_INT_DIGITS:
            raise ToolkitError(f"{_where(self, node)}: an integer of more than {MAX_INT_DIGITS} digits")
        value = super().construct_yaml_int(node)
        # 07 reads as 7 either way; 010 as 8 and 1:30 as 90, which no one writing them means
        if _BASE_8_OR_60.fullmatch(text) and (":" in text or value != int(text.replace("_", ""), 10)):
            raise ToolkitError(f"{_where(self, node)}: {text!r} would read as a base-8 or base-60 number "
                               f"({value}); write the number without leading zeros or colons")
        return value

    def construct_yaml_float(self, node):
        value = super().construct_yaml_float(node)
        if ":" in str(node.value):
            raise ToolkitError(f"{_where(self, node)}: {node.value!r} would read as a base-8 or base-60 number "
                               f"({value}); write the number without colons")
        return value


_StrictLoader.add_constructor("tag:yaml.org,2002:int", _StrictLoader.construct_yaml_int)
_StrictLoader.add_constructor("tag:yaml.org,2002:float", _StrictLoader.construct_yaml_float)


def load_yaml(text: str, source: str = "YAML") -> Any:
    """Parse one YAML document under the module's rules; ``source`` (a path, "override x=y") leads every error."""
    if len(text) > MAX_BYTES:
        raise ToolkitError(f"{source}: {len(text)} characters of YAML, more than the {MAX_BYTES} accepted")
    loader = type("Loader", (_StrictLoader,), {"source": source})(text)
    try:
        return loader.get_single_data()
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)  # where the parser gave up: line and column, counted from 1
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        what = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise YAMLSyntaxError(f"{source}: not valid YAML{where} ({what})") from None
    finally:
        loader.dispose()


def load_yaml_file(path: str | Path) -> Any:
    """:func:`load_yaml` of a file's text, which must be UTF-8 and at most ``MAX_BYTES`` long."""
    path = Path(path)
    if path.stat().st_size > MAX_BYTES:
        raise ToolkitError(f"{path}: {path.stat().st_size} bytes, more than the {MAX_BYTES} a YAML file may have")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise ToolkitError(f"{path}: not UTF-8 text (byte {e.start})") from None
    return load_yaml(text, str(path))
