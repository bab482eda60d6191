"""What a run writes and reads back: the run directory's layout (:mod:`~smoother.outputs.layout`)
and files (:mod:`~smoother.outputs.files`), the MCAP file of ROS 2 messages
(:mod:`~smoother.outputs.mcap`), the figures of a run (:mod:`~smoother.outputs.plots`), of
``smoother montecarlo`` (:mod:`~smoother.outputs.montecarlo_plot`) and of ``smoother allan``
(:mod:`~smoother.outputs.allan_plot`), on a common canvas (:mod:`~smoother.outputs.canvas`). Every
write and deletion goes through :func:`smoother.confined.inside`, which keeps it inside the
directory the user named."""
