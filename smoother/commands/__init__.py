"""Sub-commands of the ``smoother`` command line, one module each, and the checks they share:
each raises :class:`smoother.errors.UserError` naming the option, before any work starts.
:mod:`smoother.commands.run_directory` is ``smoother run``'s output directory.

Every numeric option has its range in one table, :data:`OPTION_RANGES` (closed bounds with the
unit and why, :class:`datasets.ranges.Range`, as the rig file's keys have theirs in
:data:`datasets.ranges.RANGES`; an option that mirrors a rig key takes that key's range), and is
checked against it where it is read (:func:`check_option`). ``docs/rig.md`` ("Limits") lists them.
"""
from __future__ import annotations

import os
from pathlib import Path

from datasets.ranges import RANGES, SIGMA_RANGES, Range
from smoother.errors import UserError
from smoother.online.delay import MAX_DELAY_RANGE

_SEED = Range(0, 2**32 - 1, "", "a seed of NumPy's generators: a non-negative 32-bit integer")
_WORKERS = Range(1, 1024, "", "processes or threads at once: beyond a thousand, the processes alone exhaust a "
                              "machine's memory")
_RATE = Range(1e-3, 1e4, "Hz", "a measurement rate: one in twenty minutes to 10 kHz, beyond any IMU's")

#: Every numeric command-line option's plausible range (module docstring), by the option as it is
#: typed; options with several numbers by the option and the number's name.
OPTION_RANGES: dict[str, Range] = {
    "--seed": _SEED,
    "--first-seed": _SEED,
    "--duration": Range(
        1.0, 1e8, "s",
        "a simulated recording: from the shortest a loader takes (50 IMU samples over 1 s) to over three years "
        "(2e10 samples at 200 Hz, some 20 TB for the simulation alone)"),
    "--outliers": Range(0.0, 1.0, "", "a fraction of the measurements"),
    "--start": Range(0.0, 1e8, "s", "a time in a recording, after its first IMU sample; over three years as "
                                    "--duration's bound"),
    "--end": Range(0.0, 1e8, "s", "a time in a recording, after its first IMU sample; over three years as "
                                  "--duration's bound"),
    "--gps-every": RANGES["sensor.every"],
    "--max-iterations": Range(
        1, 10_000, "",
        "Levenberg-Marquardt converges in tens of iterations; ten thousand on a long recording take hours"),
    "--max-delay": MAX_DELAY_RANGE,
    "--speed": Range(
        0.01, 1e4, "",
        "a replay's pace against the recording's own: a hundredth of it to ten thousand times it; slower does not "
        "end in a sitting, faster is the offline run (leave out --realtime)"),
    "--keyframe-rate": Range(
        1e-3, 1e4, "Hz",
        "a grid of keyframes: one in twenty minutes to 10 kHz; at most the IMU's own rate too, checked against "
        "the data"),
    "--ekf-gate": Range(
        0.5, 1.0 - 1e-12, "",
        "the probability with which the gate accepts a measurement that fits: below 0.5 it rejects most of them "
        "(at 1e-300 every one, and the EKF is dead reckoning); at 1 it gates nothing (leave it out)"),
    "--max-gyro-rate": Range(
        1.0, 1e4, "rad/s",
        "a gyro's full scale: a car turns at 1 rad/s, a MEMS gyro reads up to 35 (2000 deg/s), a spinning "
        "projectile some thousands"),
    "--pose-from-truth HZ": _RATE,
    "--pose-from-truth POS_M": SIGMA_RANGES["m"],
    "--pose-from-truth ROT_RAD": SIGMA_RANGES["rad"],
    "--gps-from-truth HZ": _RATE,
    "--gps-from-truth POS_M": SIGMA_RANGES["m"],
    "--runs": Range(2, 100_000, "", "Monte Carlo runs: at least two for a spread across them"),
    "--seeds": Range(2, 10_000, "", "seeded runs: at least two for a spread across them"),
    "--workers": _WORKERS,
    "--samples": Range(1, 1_000_000, "", "random points per Jacobian check: a million take hours"),
    "--max-dt": Range(0.0, 86_400.0, "s", "the widest time difference of associated poses: up to a day"),
    "--t-offset": RANGES["sensor.time_offset"],
    "--n-to-align": Range(1, 10**9, "", "poses to fit the alignment to"),
    "--delta": Range(1e-6, 1e9, "", "the RPE pair distance, in --delta-unit"),
}


def check_option(option: str, value) -> None:
    """``value`` of the command-line ``option`` must lie in its range in :data:`OPTION_RANGES`;
    otherwise a UserError naming the option, e.g. ``--speed: expected a value within [0.01,
    10000] (a replay's pace ...), got 1e-300``."""
    problem = OPTION_RANGES[option].problem(value)
    if problem is not None:
        raise UserError(f"{option}: {problem}")


def usable_cores() -> int:
    """The cores this process may run on (its affinity, else the machine's count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def check_workers(workers, dask_address=None) -> None:
    """``--workers``: within its range, and on this machine (no ``--dask``) at most twice its
    cores (four at least): every worker is a process of its own memory (some 300 MB with GTSAM and
    the compiled kernels loaded), and those beyond the cores only wait for them -- 1024 of them,
    the range's bound, asked for 300 GB of a 2-core machine's memory."""
    check_option("--workers", workers)
    most = max(4, 2 * usable_cores())
    if dask_address is None and workers > most:
        raise UserError(f"--workers: expected at most {most} on this machine (twice its {usable_cores()} cores: each "
                        f"worker is a process of its own memory, some 300 MB, and more only wait for the cores), "
                        f"got {workers}; a Dask cluster (--dask) takes more")


def named_directory(path) -> Path:
    """``--out`` as a path; an empty one is refused (``Path("")`` is the current directory, which
    the user did not name)."""
    if not str(path):
        raise UserError("--out: expected a directory, got an empty name (for the current directory, give --out .)")
    return Path(path)


def output_directory(path) -> Path:
    """``path`` (:func:`named_directory`) as a directory that exists (created with its parents)
    and takes new files. Called before the computation, so that a bad ``--out`` does not lose its
    results."""
    path = named_directory(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        reason = "a file of that name exists" if isinstance(error, FileExistsError) else error.strerror or error
        raise UserError(f"--out {path}: cannot create the directory ({reason})") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise UserError(f"--out {path}: the directory is not writable")
    return path
