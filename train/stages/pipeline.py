"""Stages of a run: each writes its outputs into the run directory and is skipped when they exist and
its inputs are unchanged.

A stage's *fingerprint* hashes its config section plus the fingerprints of the stages it reads from,
so changing an upstream setting re-runs everything downstream and nothing else. A stage that runs (a forced
one too) first drops the records of the stages downstream of it, since they read its old outputs. The record
``run_dir/stages/<name>.json`` (written atomically after the stage finished) holds the fingerprint and
the output files; a stage is up to date when the record matches and every output file exists.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from toolkit.errors import ToolkitError
from toolkit.io import atomic_write_json
from train.config import config_hash


@dataclass
class Stage:
    """A named step of the pipeline. ``run(ctx) -> {output_name: path relative to run_dir}``."""

    name: str
    run: Callable[["RunContext"], dict[str, str]]
    depends: tuple[str, ...] = ()
    config: Callable[[Any], Any] = lambda cfg: None  # the part of the config this stage reads


@dataclass
class RunContext:
    run_dir: Path
    config: Any
    outputs: dict[str, dict[str, str]] = field(default_factory=dict)  # stage -> {name: relative path}
    resume: bool = False
    log: Callable[[str], None] = print
    fingerprints: dict[str, str] = field(default_factory=dict)  # stage -> fingerprint, filled as the run goes

    def path(self, stage: str, name: str) -> Path:
        try:
            return self.run_dir / self.outputs[stage][name]
        except KeyError:
            raise ToolkitError(f"stage output {stage}.{name} is not available (run stage '{stage}' first)") from None


def _record_path(run_dir: Path, name: str) -> Path:
    return run_dir / "stages" / f"{name}.json"


def _finished_record(run_dir: Path, name: str) -> dict | None:
    """The stage's record when it finished and every output it wrote still exists, else None."""
    rec_path = _record_path(run_dir, name)
    try:
        record = json.loads(rec_path.read_text(encoding="utf-8")) if rec_path.exists() else None
    except (OSError, ValueError) as e:
        raise ToolkitError(f"{rec_path}: unreadable stage record ({e}); delete it to run stage '{name}' again") from None
    if record is not None and not (isinstance(record, dict) and isinstance(record.get("outputs"), dict)
                                   and all(isinstance(p, str) for p in record["outputs"].values())):
        raise ToolkitError(f"{rec_path}: expected a JSON object with an 'outputs' object of paths; delete it to run "
                           f"stage '{name}' again")
    if record is None or not all((run_dir / p).exists() for p in record["outputs"].values()):
        return None
    return record


def fingerprint(stage: Stage, cfg: Any, upstream: dict[str, str]) -> str:
    parts = [stage.name, config_hash(stage.config(cfg))] + [f"{d}:{upstream[d]}" for d in stage.depends]
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:16]


def check_dependencies(stages: list[Stage], selected: list[str], ctx: RunContext) -> None:
    """Raise for a selected stage whose unselected upstream stage, direct or read through others (eval reads the
    data, geometry, codec and estimator outputs beside the Gaussian checkpoint), is missing or stale (or
    unknown), before anything runs or is written: fingerprints depend on the config alone, not on outputs.
    :func:`run_stages` starts with it; ``train.run`` also calls it before writing the run's ``config.yaml``."""
    prints: dict[str, str] = {}
    for stage in stages:
        missing_dep = [d for d in stage.depends if d not in prints]
        if missing_dep:
            raise ToolkitError(f"stage '{stage.name}' depends on unknown stage(s) {missing_dep}")
        prints[stage.name] = fingerprint(stage, ctx.config, prints)
    needs = _unselected_upstream(stages, selected)
    for stage in stages:  # pipeline order: the first missing one is the one to run first
        if stage.name not in needs:
            continue
        d, (reader, via) = stage.name, needs[stage.name]
        who = f"stage '{reader}' needs stage '{d}'" + (f" (through stage '{via}')" if via else "")
        record = _finished_record(ctx.run_dir, d)
        if record is None:
            raise ToolkitError(f"{who}, which has not run in {ctx.run_dir}")
        if record.get("fingerprint") != prints[d]:
            raise ToolkitError(f"{who}, whose outputs in {ctx.run_dir} were made under another config than this one "
                               f"(or from other upstream outputs); re-run it too (--stages {d},...), or start from "
                               f"the run's own config (--config {ctx.run_dir / 'config.yaml'}) with the same overrides")


def _unselected_upstream(stages: list[Stage], selected: list[str]) -> dict[str, tuple[str, str | None]]:
    """Every unselected stage a selected one reads, directly or through other stages -> (that selected stage,
    the unselected stage that reads it, or None when the selected one reads it directly)."""
    needs: dict[str, tuple[str, str | None]] = {}
    for stage in reversed(stages):  # a stage's readers come after it, so they are seen first
        if stage.name in selected:
            reader = stage.name
        elif stage.name in needs:
            reader = needs[stage.name][0]
        else:
            continue
        for d in stage.depends:
            if d not in selected:
                needs.setdefault(d, (reader, None if reader == stage.name else stage.name))
    return needs


def run_stages(stages: list[Stage], selected: list[str], ctx: RunContext, force: list[str] = ()) -> dict[str, str]:
    """Run ``selected`` stages in the order of ``stages``; returns {stage: "ran" | "skipped"}.

    Dependencies not selected must already be up to date on disk (their outputs are read from the record).
    """
    by_name = {s.name: s for s in stages}
    unknown = [s for s in selected if s not in by_name]
    if unknown:
        raise ToolkitError(f"unknown stage(s) {unknown}; stages are {list(by_name)} or 'all'")
    check_run(stages, selected, ctx, force)
    prints: dict[str, str] = {}
    status: dict[str, str] = {}
    for stage in stages:
        fp = fingerprint(stage, ctx.config, prints)
        prints[stage.name] = ctx.fingerprints[stage.name] = fp
        record = _finished_record(ctx.run_dir, stage.name)
        up_to_date = record is not None and record.get("fingerprint") == fp
        if stage.name not in selected:
            if up_to_date:
                ctx.outputs[stage.name] = record["outputs"]
            continue
        if up_to_date and stage.name not in force:
            ctx.outputs[stage.name] = record["outputs"]
            ctx.log(f"[{stage.name}] up to date, skipped")
            status[stage.name] = "skipped"
            continue
        ctx.log(f"[{stage.name}] running")
        # What read this stage's old outputs is stale once it runs (a forced run too: same config, new
        # outputs), even if this run fails half-way: drop their records first, so they run again.
        for name in _dependents(stages, stage.name):
            _record_path(ctx.run_dir, name).unlink(missing_ok=True)
        t0 = time.perf_counter()
        outputs = stage.run(ctx)
        for k, p in outputs.items():
            if not (ctx.run_dir / p).exists():
                raise ToolkitError(f"stage '{stage.name}' did not write its output {k} ({p})")
        atomic_write_json(_record_path(ctx.run_dir, stage.name),
                          {"fingerprint": fp, "outputs": outputs, "seconds": time.perf_counter() - t0})
        ctx.outputs[stage.name] = outputs
        status[stage.name] = "ran"
    return status


def check_run(stages: list[Stage], selected: list[str], ctx: RunContext, force: list[str] = ()) -> set[str]:
    """Every check :func:`run_stages` makes before any stage runs (upstream stages present and current, every
    stage record it reads readable, nothing made stale half-way); ``train.run`` calls it before writing the
    run's ``config.yaml``, so a refused run leaves the directory as it was. Returns the stages that will run;
    the outputs of the current ones are in ``ctx.outputs``."""
    check_dependencies(stages, selected, ctx)
    return _check_nothing_goes_stale_midway(stages, selected, ctx, force)


def _check_nothing_goes_stale_midway(stages: list[Stage], selected: list[str], ctx: RunContext,
                                     force: list[str]) -> set[str]:
    """Refuse, before anything runs, a selection where a stage that will run feeds a stage left out of the
    selection that a selected stage reads: running the first drops the second's record (its outputs are
    stale), and the third would fail half-way through the run. Returns the stages that will run."""
    prints: dict[str, str] = {}
    will_run: set[str] = set()
    stale: dict[str, str] = {}  # unselected stage -> the stage whose re-run makes it stale
    for stage in stages:
        prints[stage.name] = fp = fingerprint(stage, ctx.config, prints)
        cause = next((d if d in will_run else stale[d] for d in stage.depends if d in will_run or d in stale), None)
        if stage.name not in selected:
            if cause is not None:
                stale[stage.name] = cause
            # run_stages reads this record too (one a re-run drops is gone by then): refuse a bad one now
            elif (record := _finished_record(ctx.run_dir, stage.name)) and record.get("fingerprint") == fp:
                ctx.outputs[stage.name] = record["outputs"]
            continue
        for d in stage.depends:
            if d in stale:
                raise ToolkitError(f"stage '{stage.name}' needs stage '{d}', which reads stage '{stale[d]}' that this "
                                   f"run re-runs: select '{d}' too (--stages ...,{d},...)")
        record = _finished_record(ctx.run_dir, stage.name)
        if cause is not None or stage.name in force or record is None or record.get("fingerprint") != fp:
            will_run.add(stage.name)
        else:
            ctx.outputs[stage.name] = record["outputs"]
    return will_run


def _dependents(stages: list[Stage], name: str) -> list[str]:
    """The stages that read ``name``'s outputs, directly or through others."""
    found: list[str] = []
    for stage in stages:  # in pipeline order: a stage's dependencies come before it
        if any(d == name or d in found for d in stage.depends):
            found.append(stage.name)
    return found


def finished_stages(stages: list[Stage], ctx: RunContext) -> list[str]:
    """Read the outputs of every stage that finished in ``ctx.run_dir`` into ``ctx.outputs``, whether or not
    its fingerprint still matches the config; returns the names of those that do not (stale: the config, or a
    config field added by a newer version of the toolkit, changed since they ran).

    For *using* a finished run (redirect, preview): what a stage wrote is what the run has, even when
    :func:`run_stages` would re-run it."""
    prints: dict[str, str] = {}
    stale = []
    for stage in stages:
        prints[stage.name] = fp = fingerprint(stage, ctx.config, prints)
        record = _finished_record(ctx.run_dir, stage.name)
        if record is None:
            continue
        ctx.outputs[stage.name] = record["outputs"]
        if record.get("fingerprint") != fp:
            stale.append(stage.name)
    return stale
