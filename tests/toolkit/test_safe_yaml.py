"""The one YAML reader: what it refuses, in one line naming the source, and that any text parses or is refused."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from toolkit.errors import ToolkitError
from toolkit.safe_yaml import MAX_DEPTH, YAMLSyntaxError, load_yaml, load_yaml_file

ROOT = Path(__file__).resolve().parents[2]

BILLION_LAUGHS = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 9)}]\n" for i in range(8)) + "seed: *i\n"


@pytest.mark.parametrize("text, says", [
    ("1: x\n", "key must be a string"),
    ("~: x\n", "key must be a string"),
    ("yes: x\n", "key must be a string"),
    ("[1, 2]: x\n", "key must be a string"),
    ("seed: 010\n", "base-8 or base-60"),
    ("seed: 1:30\n", "base-8 or base-60"),
    ("lr: 1:30.5\n", "base-60"),
    ("seed: " + "9" * 5000 + "\n", "more than 30 digits"),
    ("[" * 100_000 + "]" * 100_000, f"deeper than {MAX_DEPTH}"),
    (BILLION_LAUGHS, "aliases"),
    ("a: &x 1\nb: *x\n", "aliases"),
])
def test_refused_text_is_one_line_naming_the_source(text, says):
    t0 = time.perf_counter()
    with pytest.raises(ToolkitError, match=says) as err:
        load_yaml(text, "cfg.yaml")
    assert time.perf_counter() - t0 < 5  # refused before it expands or recurses
    msg = str(err.value)
    assert msg.startswith("cfg.yaml") and "\n" not in msg


def test_what_a_config_holds_still_reads():
    text = "seed: 0\nlr: 2.0e-3\nname: 'x'\nflags: [a, b]\nsection: {steps: 10, enabled: true}\nhex: 0x1F\nzero: 0\n"
    assert load_yaml(text) == {"seed": 0, "lr": 2e-3, "name": "x", "flags": ["a", "b"],
                               "section": {"steps": 10, "enabled": True}, "hex": 31, "zero": 0}
    assert load_yaml("'1': x") == {"1": "x"}  # a quoted key is a string
    assert load_yaml("") is None


def test_syntax_errors_are_their_own_kind():
    with pytest.raises(YAMLSyntaxError, match="not valid YAML"):
        load_yaml("a: [1, 2", "cfg.yaml")
    # where the parser gave up, for a hand-edited file: "steps: [4" then the next key on line 3
    with pytest.raises(YAMLSyntaxError, match=r"^cfg\.yaml: not valid YAML at line 3, column 5 \(expected ',' or ']'"):
        load_yaml("gaussian:\n  steps: [4\n  lr: 0.01\n", "cfg.yaml")


def test_files_must_be_utf8(tmp_path):
    bad = tmp_path / "latin1.yaml"
    bad.write_bytes("name: caf\xe9\n".encode("latin-1"))
    with pytest.raises(ToolkitError, match="not UTF-8"):
        load_yaml_file(bad)
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(bytes(range(256)))
    with pytest.raises(ToolkitError):
        load_yaml_file(binary)


@pytest.mark.fuzz
@given(st.text(alphabet=st.sampled_from(list("ab01:-[]{}&*!|>'\"#,.~ \n\t?%@`9e")), max_size=60))
def test_any_text_parses_or_is_refused_with_a_toolkit_error(text):
    try:
        load_yaml(text, "fuzz")
    except ToolkitError as e:
        assert str(e).startswith("fuzz") and "\n" not in str(e)


@pytest.mark.parametrize("text", ["1: x\n", "seed: 010\n", BILLION_LAUGHS, "[" * 5000 + "]" * 5000])
def test_the_run_cli_refuses_such_config_files_in_one_line(tmp_path, text):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(text, encoding="utf-8")
    r = subprocess.run([sys.executable, "-m", "train.run", "--config", str(cfg), "--run-dir", str(tmp_path / "run")],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, r.stderr
    assert not (tmp_path / "run").exists()
