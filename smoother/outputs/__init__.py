"""What a run writes: the run directory's files, the MCAP file of ROS 2 messages
(:mod:`~smoother.outputs.mcap`) and the figures (:mod:`~smoother.outputs.plots`)."""
