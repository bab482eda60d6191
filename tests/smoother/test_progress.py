"""Progress bars (smoother/progress.py): shown on an interactive terminal, hidden elsewhere (a log
file, a pipe, CI) unless asked for either way."""
from __future__ import annotations

import io
import sys

from smoother.progress import progress_bar


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_the_bar_shows_on_a_terminal_and_hides_on_a_pipe_unless_asked(monkeypatch):
    monkeypatch.setattr(sys, "stderr", _Terminal())
    with progress_bar(10, "batch") as shown:
        assert not shown.disable and shown.total == 10 and shown.desc == "batch" and shown.unit == "step"
    with progress_bar(10, "batch", enabled=False) as hidden:
        assert hidden.disable
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    with progress_bar(10, "batch") as piped:
        assert piped.disable
    with progress_bar(10, "batch", enabled=True) as forced:
        assert not forced.disable


def test_a_finished_bar_leaves_no_line_behind(monkeypatch):
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    with progress_bar(3, "ekf") as bar:
        for _ in range(3):
            bar.update(1)
    written = terminal.getvalue()
    assert "ekf" in written and "\n" not in written
    *_, last, after = written.split("\r")
    assert after == "" and last.strip() == ""  # the bar's line blanked: the next output starts clean
