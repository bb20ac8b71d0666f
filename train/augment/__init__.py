"""Does redirected data make a gaze estimator better? ``python -m train.run augment --run-dir RUN --out OUT``.

Two protocols on a finished run (docs/augment.md):

- **A, personal calibration** (:func:`train.augment.protocol.protocol_a`): a base estimator trained on the run's
  training subjects is fine-tuned, for each held-out person, on k of their frames (all cameras), with
  (ii) those real images alone under standard augmentation, (iii) plus the run's redirected copies of them at a
  gaze grid, (iv) plus the generator's ground-truth renders at the same gazes; scored on that person's other
  frames against (i) the base estimator.
- **B, few subjects** (:func:`train.augment.protocol.protocol_b`): estimators trained from scratch on n training
  subjects, without and with redirected copies of their frames, scored on every held-out subject.

The estimator under test has the run's design but its own seeds, disjoint from the estimator stage's, and the
arms of a comparison differ only in their training data.
"""
