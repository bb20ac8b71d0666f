"""train.data: the procedural multi-view gaze dataset and the ETH-XGaze-format HDF5 loader.

- ``train.data.synthetic``: procedural subjects (identity + expression -> meshes) rendered with exact labels.
- ``train.data.format``: the HDF5 schema (GazeGaussian-preprocessed ETH-XGaze keys), writing and validation.
- ``train.data.dataset``: ``GazeDataset`` (lazy per-sample reads, resize, white compositing, splits).
- ``train.data.pairing``: evaluation pairs (GazeNeRF protocol; generated targets for synthetic data).
- ``python -m train.data synth|inspect``.
"""
