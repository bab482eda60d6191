"""Every kind of the registry, with no list of kinds in this file: what a kind declares is what the
registry checks, and the simulator draws it (the estimators with every kind:
``tests/smoother/test_kinds_in_the_estimators.py``; ``smoother check-jacobians`` on every kind's
model: ``tests/cli/test_check_jacobians_cli.py``)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from mounted_kinds import EVERY_KIND, mounted

from datasets.kinds import KINDS, registered
from datasets.kinds.base import kind_sigmas
from datasets.simulate import simulate
from factors import sensor_models as sm

# -------------------------------------------------------------------------- the registry's rules


def _variant(kind, **changes):
    return dataclasses.replace(kind, name="variant", **changes)


@EVERY_KIND
def test_the_registry_refuses_a_kind_that_breaks_a_rule(kind):
    registered(_variant(kind))  # the kind as declared passes
    bad = {
        "twice": (lambda: registered(kind, kind), "registered twice"),
        "dimension": (lambda: registered(_variant(kind, dim=sm.MAX_RESIDUAL_DIM + 1)), "residual dimension"),
        "fields": (lambda: registered(_variant(kind, fields=kind.fields[::-1] + ("extra",))), "fields"),
        "sigma": (lambda: registered(_variant(kind, default_sigma=(-1.0,))), "default_sigma"),
        "row": (lambda: registered(_variant(kind, random_row=lambda rng: (None, np.zeros(kind.width + 1)))),
                "random_row"),
    }
    for what, (call, message) in bad.items():
        with pytest.raises(ValueError, match=message):
            call()


def test_the_registry_refuses_rows_wider_than_the_estimators_hold():
    kind = next(iter(KINDS.values()))
    wide = sm.SensorModel("wide", kind.dim, sm.MAX_ROW_WIDTH + 1, kind.model.kernel, kind.model.variables)
    with pytest.raises(ValueError, match="row width"):
        registered(_variant(kind, model=wide, random_row=lambda rng: (None, np.zeros(wide.width))))


# -------------------------------------------------------------------------- what each kind declares


@EVERY_KIND
def test_the_simulator_draws_the_kind_and_its_rows_have_the_declared_width(kind):
    data = mounted(kind).sensor("sensor").data
    assert isinstance(data, kind.data_type) and len(data) >= 29
    kind_sigmas("default_sigma", kind.default_sigma, kind.dim)
    if not kind.relative:
        assert kind.pack(data).shape == (len(data), kind.width)
    rebuilt = kind.data_type(*(getattr(data, f) for f in (*kind.times, *kind.fields)), data.cov, data.T_BS)
    for f in (*kind.times, *kind.fields, "cov"):  # a type may normalise (unit directions): to round-off
        np.testing.assert_allclose(getattr(rebuilt, f), getattr(data, f), rtol=0, atol=1e-14)


@EVERY_KIND
def test_the_simulators_shorthand_adds_a_sensor_named_after_the_kind(kind):
    d = simulate("gentle", duration=2.0, **{"pose_rate": None, f"{kind.name}_rate": 5.0})
    assert d.sensor_names == (kind.name,) and isinstance(d.sensor(kind.name).data, kind.data_type)
