"""Jobs for the spawned-process tests (train.stages.processes.run_at_once): plain functions that import nothing heavy."""

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


def unpicklable():
    import threading

    return threading.Lock()


class TwoArgError(Exception):
    def __init__(self, a, b):  # pickles, but cannot be rebuilt from its args
        super().__init__(a)
        self.b = b


def raise_two_arg():
    raise TwoArgError("needs two", 2)
