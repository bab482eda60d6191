"""Rig files written, all through ``tomlkit``, which keeps what it is not asked to change: the
user's comments, the order of the keys, blank lines and the numbers as written.

* :func:`calibrated_rig_text`: the user's rig with calibrated values in it (``calibrated.toml``).
  The file is the rig as written (:func:`datasets.rig.load_rig` checked it) with, for each
  calibrated sensor, the values the batch smoother estimated
  (:mod:`smoother.diagnosis.calibration_report`'s records): ``T_BS`` (replacing a ``camchain``),
  ``time_offset`` and ``scale``, each in place where the rig had it, else after the sensor's last
  value; its ``estimate`` and ``*_sigma`` keys become a comment there, so the next run uses the
  values as given (put them back to refine further). Paths become absolute (the file is written
  beside the run's outputs, not the rig), and a Kalibr ``imu.yaml`` gives way to the densities it
  held.
* :func:`allan_imu_block`: an ``[imu]`` table of the noise densities ``smoother allan`` measured,
  to paste into a rig file, with the per-axis values as comments above it.
"""
from __future__ import annotations

import numpy as np
import tomlkit
from tomlkit.items import Comment, Table, Whitespace

from datasets.errors import read_source
from datasets.kinds import KINDS
from datasets.kinds.base import kind_sigmas
from datasets.ranges import out_of_range
from datasets.rig import CALIBRATION_KEYS, NOISE_KEYS, Rig

#: The first lines of ``calibrated.toml``.
CALIBRATED_HEADER = ("The rig with the calibration the batch smoother estimated written in; the next run uses",
                     "these values as given.")


def _edited(table: Table, values: dict, drop=(), comments=()) -> Table:
    """``table`` with ``values`` set -- a key it has in place, keeping its comment; a new one
    after its last value -- the keys ``drop`` removed and ``comments`` (lines) after its last
    value, before the comments and blank lines that end it (those stand above the next table's
    header and belong to it)."""
    for key in drop:
        if key in table:
            del table[key]
    new = {}
    for key, value in values.items():
        if key in table:
            table[key] = value
        else:
            new[key] = value
    if not new and not comments:
        return table
    body = [(key, item) for key, item in table.value.body if key is not None or isinstance(item, (Comment, Whitespace))]
    last = max((i for i, (key, _) in enumerate(body) if key is not None), default=-1)
    out = tomlkit.table()

    def add_new() -> None:
        for key, value in new.items():
            out.add(key, value)
        for line in comments:
            out.add(tomlkit.comment(line))

    if last < 0:
        add_new()
    for i, (key, item) in enumerate(body):
        if key is None:
            out.add(item)
        else:
            out.add(key, item)
        if i == last:
            add_new()
    before, after = table.trivia, out.trivia
    after.indent, after.comment_ws, after.comment, after.trail = (before.indent, before.comment_ws, before.comment,
                                                                  before.trail)
    return out


def _rebuilt(document, tables: dict) -> tomlkit.TOMLDocument:
    """``document`` with the top-level entries ``tables`` (``{key: table or array of tables}``)
    in place of its own, everything else as it was, :data:`CALIBRATED_HEADER` first. Built as the
    parser builds a document, so that tomlkit adds no blank line of its own before a header."""
    out = tomlkit.document()
    out.parsing(True)
    for line in CALIBRATED_HEADER:
        out.add(tomlkit.comment(line))
    out.add(tomlkit.nl())
    for key, item in document.body:
        if key is None:
            out.add(item)
        else:
            out.append(key, tables.get(key.key, item))
    out.parsing(False)
    return out


def calibrated_rig_text(rig: Rig, records: dict, cautions: dict | None = None, noise: dict | None = None,
                        correlation_times: dict | None = None, correlation_fitted: tuple = ()) -> str:
    """The TOML text of ``rig`` (its file re-read, comments and layout kept) with the calibration
    ``records`` (``{sensor: record}``, :func:`smoother.diagnosis.calibration_report.calibration_records`)
    written in, and after a sensor's values, as a comment, its caution (``cautions``:
    ``{sensor: text}``, '' for none; :func:`smoother.diagnosis.calibration_report.fit_note`); with
    ``noise`` (the batch smoother's fit, ``{group: record}`` of
    :meth:`smoother.batch.variance_components.NoiseFit.record`), each density and sigma it applied
    written in its place (the IMU's densities; a sensor's ``sigma`` per axis where the rig gave
    one, else a comment with the factor on its measurements' covariances), a comment on every
    group it examined (fitted, checked and kept, or not determined by the data) and ``"noise"``
    taken out of ``estimate`` wherever it examined a group, so the next run starts from them as
    given (put it back to fit again); with ``correlation_times`` (``{sensor: seconds}``, what the run
    modelled), each one the rig does not already give written as the sensor's ``correlation_time``,
    noise and correlation time fitting together (those of ``correlation_fitted``, sensors' names,
    said to be fitted; a sensor fitted white loses its ``correlation_time = "fit"``)."""
    cautions, noise, correlation_times = cautions or {}, noise or {}, correlation_times or {}
    examined = {name: g for name, g in noise.items() if not name.startswith("_")}
    document = tomlkit.parse(read_source(rig.path, "rig").decode("utf-8-sig"))
    imu = document["imu"]
    values, drop, comments = {"source": rig.imu.source}, [], []
    if "kalibr" in imu:  # the densities it held; those the rig gave itself stay as written
        values.update({key: float(getattr(rig.imu.noise, field)) for key, field in NOISE_KEYS.items()
                       if key not in imu})
        drop.append("kalibr")
    for key, field in NOISE_KEYS.items():
        g = examined.get(f"imu.{field}")
        if g is None:
            continue
        if _fitted(g):
            values[key] = float(g["value"])
        comments.append(_noise_comment(key, g, "value"))
    if any(name.startswith("imu.") for name in examined):
        _noise_taken_out(imu, values, drop)
    tables = {"imu": _edited(imu, values, drop, comments)}
    if "sensor" in document:
        sensors = document["sensor"]
        for i, (table, config) in enumerate(zip(sensors, rig.sensors)):
            values, drop, comments = {"source": config.source}, [], []
            record = records.get(config.name)
            if record is not None:
                if "T_BS" in record:
                    values["T_BS"] = [[float(x) for x in row] for row in record["T_BS"]]
                    drop += ["camchain", "camera"]
                if "time_offset_s" in record:
                    values["time_offset"] = float(record["time_offset_s"])
                if "scale" in record:
                    values["scale"] = float(config.scale * record["scale"])
                asked = [f"{key} = {table[key].as_string()}" for key in CALIBRATION_KEYS if key in table]
                drop += [key for key in CALIBRATION_KEYS if key in table]
                comments.append("calibrated by the batch smoother; estimated with " + ", ".join(asked))
                if cautions.get(config.name):
                    comments.append(f"caution: {cautions[config.name]}")
            elif "camchain" in table:
                values["T_BS"] = [[float(x) for x in row] for row in config.T_BS]
                drop += ["camchain", "camera"]
            tau = correlation_times.get(config.name)
            if config.name in correlation_fitted:
                if tau is None:
                    drop.append("correlation_time")
                else:
                    values["correlation_time"] = float(tau)
                comments.append(f"correlation_time: {'white' if tau is None else 'this'}, fitted to the held-out "
                                'measurements (correlation_time = "fit" fits it again)')
            elif tau is not None and tau != config.correlation_time:
                values["correlation_time"] = float(tau)
                comments.append("correlation_time: as the run modelled it (--correlation-time)")
            _noise_written(table, config, {name.split(".", 1)[1]: g for name, g in examined.items()
                                           if name.split(".", 1)[0] == config.name}, values, drop, comments)
            sensors[i] = _edited(table, values, drop, comments)
        tables["sensor"] = sensors
    return tomlkit.dumps(_rebuilt(document, tables))


def _fitted(group: dict) -> bool:
    """Whether the fit changed the group's value (rather than keeping the rig's)."""
    return bool(group["applied"] and group["estimable"])


def _noise_comment(what: str, group: dict, given: str) -> str:
    """The comment line on a noise ``group`` the fit examined (``what`` it is, ``given`` what the
    rig gave: the value or the sigma): its factor, or why the rig's value stands."""
    if not group["estimable"]:
        return f"{what} not fitted by the batch smoother: {group.get('note', 'not estimable')}"
    factor = f"{group['factor']:.3g} +- {group['factor_sd']:.2g} times the {given} given"
    if group.get("steady", True) is False:
        first, second = group["halves"]
        factor += f" (not steady: x{first:.3g} in the run's first half, x{second:.3g} in its second)"
    if _fitted(group):
        return f"{what} fitted by the batch smoother: {factor}"
    return f"{what} checked by the batch smoother: {factor}; {group.get('note', 'kept')}"


def _noise_taken_out(table: Table, values: dict, drop: list) -> None:
    """``"noise"`` out of the table's ``estimate`` (the key dropped when nothing else is left): the
    fit is done, and the next run starts from its values as given."""
    if "estimate" not in table or "estimate" in drop:  # none, or dropped whole with a calibration's parts
        return
    rest = [str(part) for part in table["estimate"] if str(part) != "noise"]
    if rest:
        values["estimate"] = rest
    else:
        drop.append("estimate")


def _noise_written(table: Table, config, groups: dict, values: dict, drop: list, comments: list) -> None:
    """A sensor's ``groups`` the fit examined (``{group: record}``): the fitted ones into
    ``values`` -- its ``sigma`` per axis where the rig gave one, else its ``sigma_factor`` per axis
    on the messages' sigmas (times the one the rig gave) --, a comment on each, and ``"noise"``
    taken out of its ``estimate``."""
    if not groups:
        return
    axes = {}
    scaled = "" if config.sigma is not None else " (as sigma_factor, on its messages' sigmas)"
    for part, g in groups.items():
        if _fitted(g):
            for a in g["axes"]:
                axes[a] = g["factor"]
        comments.append(_noise_comment(f"{part} noise", g, "sigma") + (scaled if _fitted(g) else ""))
    if axes:
        dim = KINDS[config.kind].dim
        key, given = (("sigma", config.sigma) if config.sigma is not None else
                      ("sigma_factor", np.ones(1) if config.sigma_factor is None else config.sigma_factor))
        given = kind_sigmas(f"sensor {config.name!r}: {key}", given, dim)
        values[key] = [float(s * axes.get(a, 1.0)) for a, s in enumerate(given)]
    _noise_taken_out(table, values, drop)


#: Per density of :func:`allan_imu_block`: the rig file's key, the per-axis values' attribute of a
#: :class:`datasets.allan.AllanResult` and the unit.
ALLAN_KEYS = (("accel_noise_density", "acc_white", "m/s^2/sqrt(Hz), largest axis"),
              ("gyro_noise_density", "gyro_white", "rad/s/sqrt(Hz)"),
              ("accel_random_walk", "acc_walk", "m/s^3/sqrt(Hz)"),
              ("gyro_random_walk", "gyro_walk", "rad/s^2/sqrt(Hz)"))


def allan_imu_block(result, source: str, topic: str | None, n: int) -> str:
    """The densities of an Allan deviation (a :class:`datasets.allan.AllanResult` of ``n``
    samples of ``source``, ``topic``) as a rig file's ``[imu]`` table, the largest axis of each
    (:meth:`datasets.allan.AllanResult.largest`), with the per-axis values as comments; a random
    walk the data do not show is left out of the table (commented, to be filled in)."""
    largest = result.largest()
    document = tomlkit.document()
    document.parsing(True)  # the comments run straight into the header
    document.add(tomlkit.comment(f"Allan deviation of {n} samples at {1 / result.dt:.6g} Hz ({n * result.dt:.1f} s)"))
    document.add(tomlkit.comment(f"{'per axis':<28}{'x':>12}{'y':>12}{'z':>12}"))
    for key, axes, _ in ALLAN_KEYS:
        document.add(tomlkit.comment(f"{key:<28}" + "".join(f"{'-' if np.isnan(v) else f'{v:.4e}':>12}"
                                                            for v in getattr(result, axes))))
    imu = tomlkit.table()
    imu.add("source", source)
    if topic is not None:
        imu.add("topic", topic)
    for key, axes, unit in ALLAN_KEYS:
        value = largest[NOISE_KEYS[key]]
        if np.isnan(value):
            sensor = "accelerometer" if key.startswith("accel") else "gyro"
            why = [reason for reason, holds in (
                ("an axis reads one value throughout", any(a.startswith(sensor) for a in result.still)),
                ("the recording is too short", key.endswith("random_walk") and result.walk_record_s is not None))
                if holds]
            imu.add(tomlkit.comment(f"{key} = ?    # not estimated: {' and '.join(why)} (see the warning)"))
            continue
        problem = out_of_range(f"imu.{key}", value)
        if problem is not None:  # what a rig file would refuse is no value to paste
            imu.add(tomlkit.comment(f"{key} = {value:.4e}    # not usable: {problem}"))
            continue
        item = tomlkit.value(f"{value:.4e}")  # written as measured: five significant digits
        item.comment(unit)
        item.trivia.comment_ws = "    "
        imu.add(key, item)
    document.add("imu", imu)
    document.parsing(False)
    return tomlkit.dumps(document).rstrip("\n")
