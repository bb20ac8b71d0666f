from dataclasses import dataclass, field

import pytest

from toolkit import ToolkitError
from train.stages.pipeline import RunContext, Stage, finished_stages, run_stages


@dataclass
class A:
    x: int = 1


@dataclass
class Cfg:
    a: A = field(default_factory=A)
    b: int = 5


def _stages(calls):
    def mk(name, text):
        def run(ctx):
            calls.append(name)
            (ctx.run_dir / f"{name}.txt").write_text(text(ctx))
            return {"out": f"{name}.txt"}
        return run

    return [
        Stage("first", mk("first", lambda c: str(c.config.a.x)), config=lambda c: c.a),
        Stage("second", mk("second", lambda c: c.path("first", "out").read_text() + str(c.config.b)),
              depends=("first",), config=lambda c: c.b),
    ]


def test_skip_when_unchanged_and_rerun_downstream(tmp_path):
    calls = []
    ctx = lambda cfg: RunContext(tmp_path, cfg, log=lambda m: None)  # noqa: E731
    assert run_stages(_stages(calls), ["first", "second"], ctx(Cfg())) == {"first": "ran", "second": "ran"}
    assert run_stages(_stages(calls), ["first", "second"], ctx(Cfg())) == {"first": "skipped", "second": "skipped"}
    # Changing only the downstream setting re-runs only the downstream stage.
    assert run_stages(_stages(calls), ["first", "second"], ctx(Cfg(b=6))) == {"first": "skipped", "second": "ran"}
    # Changing upstream re-runs both.
    assert run_stages(_stages(calls), ["first", "second"], ctx(Cfg(a=A(2), b=6))) == {"first": "ran", "second": "ran"}
    assert (tmp_path / "second.txt").read_text() == "26"
    # A deleted output makes the stage run again.
    (tmp_path / "second.txt").unlink()
    assert run_stages(_stages(calls), ["second"], ctx(Cfg(a=A(2), b=6))) == {"second": "ran"}


def test_a_forced_upstream_stage_reruns_what_reads_it(tmp_path):
    """Same config, new outputs: whatever read the old ones must run again, now or when next selected."""
    calls = []
    ctx = RunContext(tmp_path, Cfg(), log=lambda m: None)
    run_stages(_stages(calls), ["first", "second"], ctx)
    assert run_stages(_stages(calls), ["first", "second"], ctx, force=["first"]) == {"first": "ran", "second": "ran"}
    assert run_stages(_stages(calls), ["first"], ctx, force=["first"]) == {"first": "ran"}
    assert run_stages(_stages(calls), ["second"], ctx) == {"second": "ran"}
    assert calls == ["first", "second", "first", "second", "first", "second"]


def test_a_selection_that_would_go_stale_midway_is_refused_before_anything_runs(tmp_path):
    """first -> second -> third, with second left out: re-running first would leave third reading a stale
    second, so the run is refused up front (and nothing is dropped or run)."""
    calls = []
    third = Stage("third", lambda c: calls.append("third") or (c.run_dir / "third.txt").write_text("3") and
                  {"out": "third.txt"}, depends=("second",))
    stages = [*_stages(calls), third]
    ctx = RunContext(tmp_path, Cfg(), log=lambda m: None)
    run_stages(stages, ["first", "second", "third"], ctx)
    with pytest.raises(ToolkitError, match="stage 'third' needs stage 'second', which reads stage 'first' that "
                                           "this run re-runs: select 'second' too"):
        run_stages(stages, ["first", "third"], ctx, force=["first"])
    assert calls == ["first", "second", "third"] and (tmp_path / "stages" / "second.json").exists()
    assert run_stages(stages, ["first", "second", "third"], ctx, force=["first"]) == {
        "first": "ran", "second": "ran", "third": "ran"}


def test_a_corrupt_stage_record_is_one_clear_error(tmp_path):
    run_stages(_stages([]), ["first"], RunContext(tmp_path, Cfg(), log=lambda m: None))
    (tmp_path / "stages" / "first.json").write_text("{trunc")
    with pytest.raises(ToolkitError, match=r"first\.json: unreadable stage record .*delete it"):
        run_stages(_stages([]), ["first"], RunContext(tmp_path, Cfg(), log=lambda m: None))
    for bad in ('{"fingerprint": "x"}', '{"outputs": {"checkpoint": 5}}'):
        (tmp_path / "stages" / "first.json").write_text(bad)
        with pytest.raises(ToolkitError, match=r"first\.json: expected a JSON object with an 'outputs' object"):
            run_stages(_stages([]), ["first"], RunContext(tmp_path, Cfg(), log=lambda m: None))


def test_missing_dependency_and_unknown_stage(tmp_path):
    with pytest.raises(ToolkitError, match="needs stage 'first'"):
        run_stages(_stages([]), ["second"], RunContext(tmp_path, Cfg(), log=lambda m: None))
    with pytest.raises(ToolkitError, match="unknown stage"):
        run_stages(_stages([]), ["third"], RunContext(tmp_path, Cfg(), log=lambda m: None))


def test_finished_stages_reads_stale_outputs_and_names_them(tmp_path):
    """Using a finished run (redirect, preview) must not need the config to be byte-identical to the one it
    ran under: a config field a newer toolkit adds changes every fingerprint."""
    run_stages(_stages([]), ["first", "second"], RunContext(tmp_path, Cfg(), log=lambda m: None))
    ctx = RunContext(tmp_path, Cfg(b=6), log=lambda m: None)
    assert finished_stages(_stages([]), ctx) == ["second"]
    assert ctx.path("second", "out").read_text() == "15"  # what it wrote, unchanged
    assert finished_stages(_stages([]), RunContext(tmp_path, Cfg(), log=lambda m: None)) == []
    (tmp_path / "second.txt").unlink()  # an output that is gone: not finished
    ctx = RunContext(tmp_path, Cfg(), log=lambda m: None)
    assert finished_stages(_stages([]), ctx) == [] and set(ctx.outputs) == {"first"}
