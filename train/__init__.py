"""train: the DiT-Gaze method: data, models, losses, staged training and evaluation.

Owns: the synthetic dataset and the ETH-XGaze loader (``train.data``), the two-stream Gaussian model,
the latent DiT and baseline renderers, the latent codec, losses, the intermediate gaze sampler, the gaze
estimator, ``train/run.py`` and ``train/evaluate.py``.

May import: toolkit, render, geometry.
"""
