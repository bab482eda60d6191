"""A rig file written back: the user's rig with calibrated values in it (``calibrated.toml``).

The file is the rig as read (:func:`datasets.rig.load_rig` checked it) with, for each calibrated
sensor, the values the batch smoother estimated (:mod:`smoother.calibration_report`'s records):
``T_BS`` (replacing a ``camchain``), ``time_offset`` and ``scale``; its ``estimate`` and
``*_sigma`` keys become a comment, so the next run uses the values as given (put them back to
refine further). Paths become absolute (the file is written beside the run's outputs, not the
rig), and a Kalibr ``imu.yaml`` gives way to the densities it held. Comments of the original are
not kept (TOML readers drop them).
"""
from __future__ import annotations

import json
import math
import sys

from datasets.rig import CALIBRATION_KEYS, NOISE_KEYS, Rig
from datasets.errors import read_source

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"no TOML value for {type(v).__name__}")


def _table(lines: list[str], header: str, table: dict) -> None:
    lines.append(header)
    lines.extend(f"{key} = {_value(value)}" for key, value in table.items() if not key.startswith("#"))
    lines.extend(f"# {value}" for key, value in table.items() if key.startswith("#"))
    lines.append("")


def calibrated_rig_text(rig: Rig, records: dict, cautions: dict | None = None) -> str:
    """The TOML text of ``rig`` (its file re-read) with the calibration ``records``
    (``{sensor: record}``, :func:`smoother.calibration_report.calibration_records`) written in,
    and beside a sensor's values, as a comment, its caution (``cautions``: ``{sensor: text}``,
    '' for none; :func:`smoother.calibration_report.fit_note`)."""
    cautions = cautions or {}
    raw = tomllib.loads(read_source(rig.path, "rig").decode("utf-8"))
    imu = dict(raw["imu"])
    imu["source"] = rig.imu.source
    if "kalibr" in imu:
        del imu["kalibr"]
        for key, field in NOISE_KEYS.items():
            imu[key] = float(getattr(rig.imu.noise, field))
    lines = ["# The rig with the calibration the batch smoother estimated written in; the next run uses",
             "# these values as given.", ""]
    _table(lines, "[imu]", imu)
    if "datum" in raw:
        _table(lines, "[datum]", raw["datum"])
    for table, config in zip(raw.get("sensor", []), rig.sensors):
        out = dict(table)
        out["source"] = config.source
        record = records.get(config.name)
        if record is not None:
            if "T_BS" in record:
                out.pop("camchain", None)
                out.pop("camera", None)
                out["T_BS"] = [[float(x) for x in row] for row in record["T_BS"]]
            if "time_offset_s" in record:
                out["time_offset"] = float(record["time_offset_s"])
            if "scale" in record:
                out["scale"] = float(config.scale * record["scale"])
            asked = {key: out.pop(key) for key in CALIBRATION_KEYS if key in out}
            out["# calibrated"] = ("calibrated by the batch smoother; estimated with "
                                   + ", ".join(f"{k} = {_value(v)}" for k, v in asked.items()))
            if cautions.get(config.name):
                out["# caution"] = f"caution: {cautions[config.name]}"
        elif "camchain" in out:
            out["T_BS"] = [[float(x) for x in row] for row in config.T_BS]
            out.pop("camchain")
            out.pop("camera", None)
        _table(lines, "[[sensor]]", out)
    return "\n".join(lines)
