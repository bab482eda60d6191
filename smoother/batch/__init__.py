"""The batch smoother: the whole graph optimised at once (:mod:`~smoother.batch.solve`) by one of
the optimisers (:mod:`~smoother.batch.optimiser`, named in :mod:`~smoother.batch.methods`), with
marginal covariances of every keyframe."""
