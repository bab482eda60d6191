"""The sliding window's kernels compiled in a second process (smoother/online/warm_up.py): when
a child starts, and that the run waits for it and stops it (that its cache is the one the run
loads: tests/cli/test_kernel_layouts.py, which pays for a first run already)."""
from __future__ import annotations

from types import SimpleNamespace

import pytest

from smoother import pipeline
from smoother.online import warm_up as kernel_warm_up


class _Child:
    """A stand-in warm-up child that records what the run did with it."""

    def __init__(self):
        self.calls = []

    def wait(self):
        self.calls.append("wait")

    def close(self):
        self.calls.append("close")


@pytest.mark.parametrize("order, kind, cold, cores, starts", [
    (["ekf", "batch", "fixed-lag"], "sliding", True, 2, True),
    (["fixed-lag"], "sliding", True, 2, False),  # nothing to overlap with
    (["fixed-lag", "ekf"], "sliding", True, 2, False),
    (["ekf", "fixed-lag"], "incremental", True, 2, False),  # GTSAM's smoother: no window kernels
    (["ekf", "fixed-lag"], "sliding", False, 2, False),  # on disk already
    (["ekf", "fixed-lag"], "sliding", True, 1, False),  # one thread (BOXPLUS_THREADS=1): it would only compete
])
def test_a_child_starts_only_when_the_window_runs_after_others_with_its_kernels_not_on_disk(
        monkeypatch, order, kind, cold, cores, starts):
    started = []
    monkeypatch.setattr(kernel_warm_up, "cold", lambda: cold)
    monkeypatch.setattr(kernel_warm_up, "thread_count", lambda: cores)
    monkeypatch.setattr(kernel_warm_up.subprocess, "Popen", lambda *a, **k: started.append(a) or object())
    assert (kernel_warm_up.start(order, kind) is not None) == starts
    assert len(started) == starts


def test_the_run_waits_for_the_child_before_the_fixed_lag_smoother_and_stops_it_at_the_end(monkeypatch):
    from smoother.diagnosis import mounting

    child, seen = _Child(), []
    monkeypatch.setattr(pipeline.kernel_warm_up, "start", lambda order, kind: child)
    monkeypatch.setattr(mounting, "check_mountings", lambda dataset: mounting.MountingCheck(()))
    for name in ("ekf", "batch", "fixed-lag"):
        monkeypatch.setattr(pipeline, f"_{name.replace('-', '_')}",
                            lambda *a, name=name, **k: seen.append((name, list(child.calls)))
                            or pipeline.Estimate(name, None, 0.0, {}))
    dataset = SimpleNamespace(noise_to_estimate=(), correlation_to_fit=(), sensors=())
    out = dict(pipeline.estimate_each(dataset, ["ekf", "batch", "fixed-lag"]))
    assert list(out) == ["ekf", "batch", "fixed-lag"]
    assert seen == [("ekf", []), ("batch", []), ("fixed-lag", ["wait"])]
    assert child.calls == ["wait", "close"]
