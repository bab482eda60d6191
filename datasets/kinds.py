"""The measurement kinds a rig file or the command line can name.

Each kind is declared once here; the graph, the EKF, the simulator, the rig loader and the
command line iterate over this declaration.
"""
from __future__ import annotations

#: The kinds of aiding sensor, by the name a rig file's ``kind`` and the command line use.
KIND_NAMES = ("pose", "position", "gnss", "orientation", "velocity", "odometry")
