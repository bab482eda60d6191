"""Fixtures of the datasets tests: ``isolated``, which runs a reader on hostile input where a
regression can neither hang the test run nor exhaust its memory (:func:`isolation.isolated`)."""
from __future__ import annotations

import pytest
from isolation import isolated as _isolated


@pytest.fixture
def isolated():
    """``isolated(call, seconds=10, memory=2 GiB)``: :func:`isolation.isolated`."""
    return _isolated
