"""The layout of a run directory: the name of every file ``smoother run`` writes into it (and
``smoother plot`` with ``--out`` left out), in one place for the code that writes them
(:mod:`smoother.outputs.files`, :mod:`smoother.outputs.mcap`, :mod:`smoother.outputs.plots`),
reads them (:func:`smoother.outputs.files.load_run`) and keeps the directory to one run
(:mod:`smoother.commands.run_directory`)."""
from __future__ import annotations

#: What a run writes per estimator, after the estimator's name: its TUM trajectory, its states
#: and covariances, its GeoJSON line (with a GNSS datum).
ESTIMATE_SUFFIXES = (".tum", ".npz", ".geojson")
#: The ground truth, where known.
TRUTH = "truth.npz"
#: The dataset's position fixes, used and held out, where it has any.
GPS = "gps.npz"
#: The scores of every estimator and the run's record (written last).
METRICS = "metrics.json"
#: The run's estimates as ROS 2 messages (``--mcap``).
MCAP = "estimates.mcap"
#: The rig with the batch smoother's calibration written in (a rig run that estimates one).
CALIBRATED_RIG = "calibrated.toml"
#: The plots of a run (:func:`smoother.outputs.plots.plot_run`), each ``<name>.png``, in the order
#: they are drawn.
PLOTS = ("trajectory", "position_error", "orientation_error", "nees", "biases", "comparison")
