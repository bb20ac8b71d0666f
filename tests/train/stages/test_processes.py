"""Jobs run at once in spawned processes (train.stages.processes)."""

import pytest

from toolkit import ToolkitError
from train.stages.processes import run_at_once


def test_run_at_once_returns_in_order_and_a_failure_stops_the_others(tmp_path):
    """Results come back in job order; the first failure is raised at once, the other job is stopped rather than
    waited for (its marker file never appears), and a process that dies is a one-line ToolkitError."""
    from tests.train import procs

    assert run_at_once([(procs.echo, {"value": 1}), (procs.echo, {"value": "b"})]) == [1, "b"]
    marker = tmp_path / "finished"
    slow = (procs.sleep_then_touch, {"seconds": 30, "path": str(marker)})
    with pytest.raises(ValueError, match="job failed"):
        run_at_once([slow, (procs.fail, {})])
    with pytest.raises(ToolkitError, match="a worker process died"):
        run_at_once([slow, (procs.die, {})])
    assert not marker.exists()
    # What cannot make the trip back comes back as an error, never as a hang or a misleading TypeError.
    with pytest.raises(TypeError, match="cannot pickle"):
        run_at_once([(procs.unpicklable, {})])
    with pytest.raises(RuntimeError, match="TwoArgError: needs two"):
        run_at_once([(procs.raise_two_arg, {})])
