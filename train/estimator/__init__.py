"""train.estimator: the gaze estimator — a compact CNN (no torchvision), its crops, augmentation and training,
and drawn 2D faces for cheap labelled images."""
