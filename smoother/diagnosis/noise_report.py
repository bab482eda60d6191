"""What a run says of the noise the batch smoother fitted (``metrics.json``'s ``batch.noise``,
:meth:`smoother.batch.variance_components.NoiseFit.record`): one printed line per group, after the
calibration table.

Each line gives the group, the density or sigma in use (the rig's units: the fitted one where it
was applied, else the rig's), the factor the data give on the value given with its standard
deviation and the degrees of freedom its residuals carry, then what
became of it: applied, kept at the rig's value (consistent with it, or not estimable, and why),
merged with another component, or not applied as a model error with its likely cause
(:mod:`smoother.diagnosis.noise_honesty`); and where the run's two halves ask for different noise,
each half's factor.
"""
from __future__ import annotations


def noise_lines(record: dict) -> list[str]:
    """The printed lines of a noise fit's ``record`` (``{group: record, "_fit": ...}``)."""
    fit = record.get("_fit", {})
    fits = fit.get("fits", 1)
    again = f" in {fits} fits, each with the model errors found before it held" if fits > 1 else ""
    lines = [f"noise fitted by the batch smoother ({fit.get('iterations', '?')} iterations{again}"
             f"{'' if fit.get('converged', True) else ', NOT converged'}):"]
    for name, g in record.items():
        if name.startswith("_"):
            continue
        value = "" if g.get("value") is None else f"{g['value']:.3g} {g['unit']}".rstrip()
        if not g["estimable"]:
            lines.append(f"  {name:<28} {value:<22} kept: {g.get('note', 'not estimable')}")
            continue
        figure = f"x{g['factor']:.3g} +- {g['factor_sd']:.2g} (redundancy {g['redundancy']:.3g})"
        if g["merged_with"]:
            figure += f", one factor with {', '.join(g['merged_with'])}"
        if g["applied"]:
            what = "applied" + (f"; {g['note']}" if g.get("note") else "")
        else:
            what = g.get("note", "not applied")
        lines.append(f"  {name:<28} {value:<22} {figure}: {what}{unsteady(g)}")
    return lines


def unsteady(g: dict) -> str:
    """``"; not steady: ..."`` for a group whose two halves of the run ask for different noise
    (:func:`smoother.batch.variance_components._halves`), else ''."""
    if g.get("steady", True) or g.get("halves") is None:
        return ""
    first, second = g["halves"]
    return (f"; not steady: x{first:.3g} in the run's first half, x{second:.3g} in its second (one value "
            "over the run is their average, and a run of other data may find it out of band)")


def fitted_sensors(record: dict | None) -> dict[str, str]:
    """Per sensor whose noise the fit's ``record`` holds (the IMU's too), what became of its groups,
    in a phrase for the run's warnings: ``"ahrs.attitude not estimable"``, ``"wheels.forward x10.6,
    wheels.vertical kept"`` (kept: at the rig's value, consistent with it or a model error). Empty
    without a fit."""
    out: dict[str, list[str]] = {}
    for name, g in (record or {}).items():
        if name.startswith("_"):
            continue
        status = ("not estimable" if not g["estimable"] else f"x{g['factor']:.3g}" if g["applied"] else "kept")
        out.setdefault(g["sensor"], []).append(f"{name} {status}")
    return {sensor: ", ".join(parts) for sensor, parts in out.items()}
