"""train.data: the procedural multi-view gaze dataset and the ETH-XGaze-format HDF5 loader.

- ``train.data.synthetic``: procedural subjects (identity + expression -> meshes) rendered with exact labels;
  their parameters and codes in ``train.data.subject_params``, poses and cameras in ``train.data.poses``, mesh
  pieces in ``train.data.head_mesh``.
- ``train.data.generate``: the synthetic dataset (subjects, frames, cameras) written as HDF5 files.
- ``train.data.format``: the HDF5 schema (GazeGaussian-preprocessed ETH-XGaze keys), writing and validation.
- ``train.data.layouts``: the peers' layouts (GazeGaussian, GazeNeRF, the ETH-XGaze release) as data, and their
  detection; ``train.data.layout_conversion`` to and from the native conventions (``train.data.triangulation``:
  GazeNeRF's 3D landmarks); ``train.data.layout_files``: their split files, the layout a stage reads.
- ``train.data.dataset``: ``GazeDataset`` (lazy per-sample reads, resize, white compositing, splits).
- ``train.data.rows``: ``RowSource`` / ``RowImages``, a split's rows read a batch at a time (bounded cache,
  reading threads) for the stages that train on it.
- ``train.data.patches``: the ETH-XGaze release's face patches and labels, read lazily for the estimator stage.
- ``train.data.export``: native files written in a peer's layout (``python -m train.data export``).
- ``train.data.pairing``: evaluation pairs (GazeNeRF protocol; generated targets for synthetic data).
- ``python -m train.data synth|inspect|export``.
"""
