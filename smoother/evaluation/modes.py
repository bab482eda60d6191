"""The alignments of an estimate onto its reference and the units of the relative pose error's
distance, by the names :func:`smoother.evaluation.metrics.evaluate` and ``smoother evaluate``
(``--align``, ``--delta-unit``) take (:mod:`smoother.evaluation.metrics` defines each). A module
of its own so that the command line lists them without importing Numba."""

ALIGN_MODES = ("se3", "sim3", "posyaw", "translation", "none")
DELTA_UNITS = ("frames", "m", "s")
