"""train: the DiT-Gaze method: data, models, losses, staged training and evaluation.

Owns, one subpackage a job: ``train.data`` (the synthetic dataset, the subject-file loader, evaluation
pairing), ``train.model`` (two-stream Gaussian model, fields, DiT and U-Net renderers, diffusion, codecs),
``train.losses`` (image, gaze and orthogonality losses, metrics, LPIPS, VGG, identity), ``train.estimator``
(the gaze estimator), ``train.training`` (trainer, intermediate-gaze sampler, loop, checkpoints, DDP),
``train.stages`` (the pipeline and one module per stage), ``train.evaluation`` (protocol, test-time fitting,
report, figures, FID); the run configuration (``train.config``, ``train.run_config``), the CLI
(``train.run``) and ``train.trained_run.TrainedRun``, which opens a finished run for apps and benchmarks.

May import: toolkit, render, geometry.
"""
