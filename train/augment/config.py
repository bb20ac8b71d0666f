"""The augmentation benchmark's settings: one dataclass, its command line generated from its fields."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field, fields

from toolkit.errors import CliParser, ToolkitError
from train.config import at_least, check_fields, within
from train.run_config import DEVICE, SEED, STEP_CAP

COUNT = at_least(1, "a count")
STEPS = at_least(0, "a step count") | STEP_CAP


@dataclass
class AugmentConfig:
    ks: tuple[int, ...] = (1, 3, 9)
    """calibration frames per held-out person (protocol A); a k not below the person's frame count is skipped,
    as the person's other frames are the test set."""
    seeds: int = field(default=3, metadata=within(1, 100, "a count"))
    """repetitions, each with its own estimator seed and its own draw of calibration frames, 1 to 100."""
    grid: int = field(default=3, metadata=within(1, 15, "gazes per axis"))
    """gazes per axis of the redirection grid (grid x grid head-frame gazes), 1 to 15."""
    grid_deg: float = field(default=25.0, metadata=within(0, 60, "degrees"))
    """half-width of the gaze grid, degrees in [0, 60]: pitch and yaw in [-grid_deg, grid_deg]."""
    redirect_cameras: int = field(default=3, metadata=within(1, 1000, "a camera count"))
    """cameras of each calibration (or training) frame whose images get redirected copies, >= 1: each costs one
    test-time fit (protocol A), so this bounds the run time; spread evenly over the frame's cameras (at most
    all of them), 1 to 1000."""
    fit_steps: int = field(default=0, metadata=STEPS)
    """test-time fitting steps per redirected input, the natural fit without a gaze term; 0: the run's
    ``eval.tta_steps``."""
    base_steps: int = field(default=0, metadata=STEPS)
    """training steps of the base estimator (and of protocol B's); 0: the run's ``estimator.steps``."""
    warmup_steps: int = field(default=100, metadata=STEPS)
    """linear learning-rate warm-up of every estimator trained from scratch (protocol A's base, protocol B's),
    steps >= 0: without it some seeds diverge in their first steps and never recover (one protocol B
    estimator ended at 34 deg; docs/results.md, 2026-11-27). Fine-tuning starts at its low rate."""
    tune_steps: int = field(default=60, metadata=COUNT | STEP_CAP)
    """fine-tuning steps of every protocol A arm, >= 1 (the same for all arms); 300 at 5e-4 over-fitted the
    control to 3x the base's error on the demo (docs/results.md, 2026-11-27)."""
    tune_lr: float = field(default=1e-4, metadata=within(0, 1, "a learning rate", low_open=True))
    """fine-tuning learning rate (cosine-decayed), in (0, 1]."""
    subjects: tuple[int, ...] = (2, 4, 8)
    """training subjects of protocol B's estimators; a count above the run's training subjects is skipped."""
    protocols: tuple[str, ...] = ("A", "B")
    """which protocols to run: A, B or both."""
    device: str = field(default="auto", metadata=DEVICE)
    """where the estimators train and the run's model renders: auto (CUDA when available), cpu, cuda or cuda:N."""
    seed: int = field(default=0, metadata=SEED)
    """base seed of the benchmark, in [0, 2^32) (estimator seeds are 1000 + 10 x seed + repetition: disjoint from the stage's)."""

    def validate(self) -> None:
        check_fields(self, "augment --", spell=lambda name: name.replace("_", "-"))
        for name, values, low in (("ks", self.ks, 1), ("subjects", self.subjects, 1)):
            if not values or any(int(v) != v or v < low for v in values):
                raise ToolkitError(f"augment --{name}: expected integers >= {low}, got {list(values)}")
        bad = set(self.protocols) - {"A", "B"}
        if bad or not self.protocols:
            raise ToolkitError(f"augment --protocols: expected A, B or both, got {list(self.protocols)}")


def build_parser() -> argparse.ArgumentParser:
    """``train.run augment``'s parser: ``--run-dir``, ``--out`` and one flag per field."""
    p = CliParser(prog="python -m train.run augment",
                  description="Measure whether redirected data makes a gaze estimator better "
                                            "(docs/augment.md). On the demo run, protocol A with its defaults "
                                            "(3 repetitions) took 12.3 min on an idle 2-core machine.")
    p.add_argument("--run-dir", required=True, help="a finished run directory")
    p.add_argument("--out", required=True, help="output folder: augment.json, augment.md, augment.png")
    docs = _field_docs()
    for f in fields(AugmentConfig):
        flag = "--" + f.name.replace("_", "-")
        doc = " ".join(docs.get(f.name, "").split())
        if f.name in ("ks", "subjects"):
            p.add_argument(flag, type=int, nargs="+", default=list(f.default), help=doc)
        elif f.name == "protocols":
            p.add_argument(flag, nargs="+", default=list(f.default), help=doc)
        else:
            p.add_argument(flag, type=type(f.default), default=f.default, help=doc)
    return p


def config_from_args(args: argparse.Namespace) -> AugmentConfig:
    cfg = AugmentConfig(**{f.name: (tuple(getattr(args, f.name)) if isinstance(f.default, tuple)
                                    else getattr(args, f.name)) for f in fields(AugmentConfig)})
    cfg.validate()
    return cfg


def _field_docs() -> dict[str, str]:
    """{field: its docstring} (the string literal after each field in the class body), for ``--help``."""
    import ast
    import inspect

    body = ast.parse(inspect.getsource(AugmentConfig)).body[0].body
    return {node.target.id: str(nxt.value.value) for node, nxt in zip(body, body[1:])
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
            and isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)}
