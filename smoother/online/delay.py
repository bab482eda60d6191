"""How late a measurement may arrive at an online smoother (``OnlineSmoother(max_delay_s=...)``,
``smoother run --max-delay``): one range for both, in a module light enough for the command line
to read at start."""
from datasets.ranges import Range

#: The range of ``max_delay_s``: a link delays a measurement by milliseconds to seconds; one a
#: minute late is no longer online, and every IMU sample waits in memory that long before its
#: keyframe is made (at an infinite delay none ever is).
MAX_DELAY_RANGE = Range(0.0, 60.0, "s", "how late a measurement may arrive: a link delays by milliseconds to "
                                       "seconds; a minute late is no longer online, and every IMU sample waits in "
                                       "memory that long (at inf no keyframe is ever made)")
