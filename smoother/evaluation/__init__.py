"""How good is an estimate? Trajectory metrics as evo computes them
(:mod:`~smoother.evaluation.metrics`, the names of its alignments in
:mod:`~smoother.evaluation.modes`), scores against a dataset's reference
(:mod:`~smoother.evaluation.scoring`), the estimators' cross-check
(:mod:`~smoother.evaluation.crosscheck`), Monte Carlo runs (:mod:`~smoother.evaluation.montecarlo`)
and GTSAM's native IMU path as a reference (:mod:`~smoother.evaluation.native`)."""
