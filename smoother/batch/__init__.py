"""The batch smoother: the whole graph optimised at once (:mod:`~smoother.batch.solve`), with
marginal covariances of every keyframe."""
