"""train.training: the machinery of the long Gaussian-stage training — the trainer, the intermediate-gaze sampler,
the resumable loop, checkpoints, DDP and the weight average."""
