"""train.stages: the pipeline of a run — the stage runner (``pipeline``) and one module per stage."""
