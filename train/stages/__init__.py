"""train.stages: the pipeline of a run — the stage runner (``pipeline``), one module per stage, and the
stage table.

Each stage writes its outputs into the run directory and is skipped when they exist and its inputs (its
config section and the stages it reads) are unchanged; a stage's fingerprint hashes exactly those.

The stages, in order: ``data``, ``geometry``, ``codec``, ``estimator``, ``gaussian``, ``eval``; each module's
docstring says what its stage writes, and ``python -m train.run --help`` lists them.
"""

from train.stages.codec import stage_codec
from train.stages.data import stage_data
from train.stages.estimator import stage_estimator
from train.stages.eval import stage_eval
from train.stages.gaussian import GAUSSIAN_INPUTS, gaussian_section, stage_gaussian
from train.stages.geometry import geometry_section, stage_geometry
from train.stages.pipeline import Stage

STAGES = [
    # Stage(name, body, the stages it reads, the part of the config it reads)
    Stage("data", stage_data, config=lambda c: c.data),
    Stage("geometry", stage_geometry, ("data",), config=geometry_section),
    Stage("codec", stage_codec, ("data",), config=lambda c: (c.seed, c.codec)),
    Stage("estimator", stage_estimator, ("data",), config=lambda c: (c.seed, c.estimator)),
    # ("geometry", "codec", "estimator") and (seed, gaussian): declared beside the stage, whose checkpoints'
    # resume key hashes them too.
    Stage("gaussian", stage_gaussian, GAUSSIAN_INPUTS, config=gaussian_section),
    Stage("eval", stage_eval, ("gaussian",), config=lambda c: c.eval),
]
"""The stages of a run, in the order they run."""

STAGE_NAMES = tuple(s.name for s in STAGES)
