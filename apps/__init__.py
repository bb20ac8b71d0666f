"""apps: the programs a person runs: the demo (``demo``), live gaze preview (``preview``, with the scene in
``gaze_scene``, the headless sweep in ``preview_sweep``, the window in ``preview_window``) and dataset
redirection (``redirect``, with ``redirect_render``, ``redirect_parts``, and the crops' CSV: read in
``labels_table``, turned into inputs in ``labels_csv``).
A trained run is opened with ``train.trained_run.TrainedRun``: no app reaches into train's private names.

May import: anything (toolkit, render, geometry, train).
"""
