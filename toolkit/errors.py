"""The project's one exception type and the CLI wrapper that turns it into a one-line error."""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import sys
from typing import Callable, Sequence


class ToolkitError(Exception):
    """A problem with the user's input or environment, worded so the user can act on it.

    The message names the file or field and what was expected; CLIs print it as one line
    (``error: ...``) and exit with status 2.
    """


class CliParser(argparse.ArgumentParser):
    """The commands' argument parser: a usage mistake is one ``error:`` line naming the way to the options (a
    ``ToolkitError``, exit status 2 through :func:`run_cli`) rather than argparse's usage block, and an option is
    never taken from a prefix of its name (``--subject 2`` is refused, not read as ``--subjects 2``)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        if message.endswith("expected one argument"):  # most often a value that starts with '-', read as a flag
            message += " (a value starting with '-' is written --flag=VALUE, e.g. --yaw=-30:30:5)"
        raise ToolkitError(f"{message} (`{self.prog} --help` lists the options)")


def bad_rows_error(problems: list[tuple[int, str]]) -> ToolkitError:
    """One error for a table's bad rows, ``(line, message)`` each, every row checked: the first row's message,
    then the other lines with problems, so one run shows all that needs mending."""
    more = [str(line) for line, _ in problems[1:]]
    tail = f" (and {len(more)} more line(s) with problems: {', '.join(more[:10])}{', ...' if len(more) > 10 else ''})"
    return ToolkitError(problems[0][1] + (tail if more else ""))


def one_line(e: BaseException | str, limit: int | None = 200) -> str:
    """A library's message as one plain line, to quote in a ``ToolkitError``: terminal colour codes dropped, line
    breaks and runs of blanks made single spaces, cut at ``limit`` characters (None: whole). torch's state-dict
    and unpickling errors span lines and colour their text; HDF5's carry a time stamp line."""
    text = re.sub(r"\x1b\[[0-9;]*[A-Za-z]", "", str(e))
    text = " ".join("".join(c if c.isprintable() else " " for c in text).split())
    return text if limit is None or len(text) <= limit else text[:limit] + "..."


OUR_PACKAGES = ("toolkit", "render", "geometry", "train", "apps", "benchmarks")


ERROR_FILE_ENV = "DITGAZE_ERROR_FILE"
"""When set, :func:`run_cli` writes its error line's text to that file instead of stderr: for a parent that runs
the command as a child process and reports the failure as its own one line (``train.ablate``)."""


def _report(text: str) -> None:
    if path := os.environ.get(ERROR_FILE_ENV):
        with contextlib.suppress(OSError):
            with open(path, "w", encoding="utf-8") as f:
                f.write(text)
            return
    print(f"error: {text}", file=sys.stderr)


def run_cli(main: Callable[[Sequence[str] | None], int | None], argv: Sequence[str] | None = None) -> int:
    """Run a CLI entry point; ``ToolkitError``, a missing package, a file-system error on a named path and Ctrl-C
    become one line on stderr (or in :data:`ERROR_FILE_ENV`'s file), never a traceback."""
    try:
        code = main(argv)
    except ToolkitError as e:
        _report(str(e))
        return 2
    except ModuleNotFoundError as e:
        if (e.name or "").split(".")[0] in OUR_PACKAGES:
            raise  # a broken import of our own code is a bug, not a missing install
        # Heavy dependencies (open3d, pymeshlab, trimesh, glfw) are imported lazily, inside the command that needs
        # them, so a partial install fails here rather than at start-up.
        _report(f"this command needs the Python package {e.name!r}, which is not installed "
                "(`make setup` installs every dependency)")
        return 2
    except BrokenPipeError:
        # The reader went away (`... | head`): stop quietly, as cat does. Point stdout at /dev/null so the
        # interpreter's own flush at exit does not fail on the closed pipe a second time.
        with contextlib.suppress(OSError, ValueError, AttributeError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except OSError as e:
        if e.filename is None:
            raise  # not about a path the user gave: a bug or a system fault, keep its traceback
        # A path the user gave that the system refuses (a file where a folder should be, no permission, a full disk).
        _report(f"{e.filename}: {e.strerror or e}")
        return 2
    except KeyboardInterrupt:
        _report("interrupted")
        return 130
    return int(code or 0)
