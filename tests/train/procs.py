"""Jobs for the spawned-process tests (train.run.run_at_once): plain functions that import nothing heavy."""

import os
import time
from pathlib import Path


def echo(value):
    return value


def fail():
    raise ValueError("job failed")


def die():
    os._exit(3)  # no exception: the process is just gone


def sleep_then_touch(seconds: float, path: str):
    time.sleep(seconds)
    Path(path).touch()
    return "slept"
