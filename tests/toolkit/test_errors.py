"""The CLI wrapper: every expected failure is one line on stderr with a non-zero status."""

import pytest

from toolkit.errors import ToolkitError, run_cli


def _raises(exc):
    def main(argv):
        raise exc

    return main


@pytest.mark.parametrize("exc, code, text", [
    (ToolkitError("data.h5: field 'gaze' expected [N, 2]"), 2, "error: data.h5: field 'gaze' expected [N, 2]"),
    (ModuleNotFoundError("No module named 'open3d'", name="open3d"), 2, "needs the Python package 'open3d'"),
    (KeyboardInterrupt(), 130, "error: interrupted"),
    (FileExistsError(17, "File exists", "out/demo"), 2, "error: out/demo: File exists"),
])
def test_expected_failures_are_one_line(capsys, exc, code, text):
    assert run_cli(_raises(exc), []) == code
    err = capsys.readouterr().err
    assert text in err and err.count("\n") == 1 and "Traceback" not in err


def test_a_parent_can_take_the_error_line_through_a_file(capsys, monkeypatch, tmp_path):
    """With the error-file variable set (a parent running the CLI as its child), the line goes to that file."""
    from toolkit.errors import ERROR_FILE_ENV

    monkeypatch.setenv(ERROR_FILE_ENV, str(tmp_path / "error"))
    assert run_cli(_raises(ToolkitError("gaussian.lr: expected a number")), []) == 2
    assert (tmp_path / "error").read_text() == "gaussian.lr: expected a number" and capsys.readouterr().err == ""
    monkeypatch.setenv(ERROR_FILE_ENV, str(tmp_path / "missing" / "error"))  # unwritable: stderr as always
    assert run_cli(_raises(ToolkitError("x")), []) == 2 and capsys.readouterr().err == "error: x\n"


def test_exit_codes_pass_through_and_bugs_still_raise():
    assert run_cli(lambda argv: None, []) == 0
    assert run_cli(lambda argv: 3, []) == 3
    with pytest.raises(ValueError):  # a bug in our code is not hidden behind a one-line message
        run_cli(_raises(ValueError("bug")), [])
    with pytest.raises(OSError):  # nor is a system error that names no path the user gave
        run_cli(_raises(OSError(5, "Input/output error")), [])
    with pytest.raises(ModuleNotFoundError):  # nor is a broken import of our own modules
        run_cli(_raises(ModuleNotFoundError("No module named 'train.nope'", name="train.nope")), [])


def test_a_closed_pipe_stops_quietly():
    """`... | head`: the reader leaves early; the CLI stops without a BrokenPipeError traceback."""
    import subprocess
    import sys
    from pathlib import Path

    code = ("import sys\nfrom toolkit.errors import run_cli\n"
            "def main(argv):\n    for _ in range(200000):\n        print('x' * 80)\n"
            "sys.exit(run_cli(main))\n")
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         cwd=Path(__file__).resolve().parents[2])
    p.stdout.read(100)
    p.stdout.close()
    err = p.stderr.read().decode()
    assert p.wait(timeout=60) == 1 and err == "", err


@pytest.mark.parametrize("argv, text", [
    ([], "error: the following arguments are required: --count (`tool --help` lists the options)"),
    (["--count", "x"], "error: argument --count: invalid int value: 'x' (`tool --help` lists the options)"),
    (["--count", "1", "--coun=2"], "error: unrecognized arguments: --coun=2"),  # a prefix is not the option
    (["sub", "--size", "9"], "error: argument --size: invalid choice: 9 (choose from 1, 2) (`tool sub --help`"),
    (["--count", "-x"], "error: argument --count: expected one argument (a value starting with '-' is written "
                        "--flag=VALUE"),
])
def test_usage_mistakes_are_one_line_naming_the_help(capsys, argv, text):
    from toolkit.errors import CliParser

    def main(args):
        ap = CliParser(prog="tool")
        ap.add_argument("--count", type=int, required=not args or args[0] != "sub")
        sub = ap.add_subparsers(dest="cmd")
        sub.add_parser("sub").add_argument("--size", type=int, choices=[1, 2])
        ap.parse_args(args)
        return 0

    assert run_cli(main, argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(text) and err.count("\n") == 1, err
