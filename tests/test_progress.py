"""Progress bars: a rate and an ETA on a terminal, nothing at all otherwise."""

import io

from experiments.common import ProgressBar


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_progress_bar_shows_rate_and_eta_on_a_terminal(monkeypatch):
    term = _Terminal()
    monkeypatch.setattr("sys.stderr", term)
    bar = ProgressBar("stage 0: 24 flights", unit="tick")
    for k in range(1, 51):
        bar(k, 50)
    text = term.getvalue()
    assert "stage 0: 24 flights" in text and "50/50" in text and "tick/s" in text
    assert "<" in text  # tqdm's "elapsed<remaining" ETA field


def test_progress_bar_is_quiet_when_not_on_a_terminal(monkeypatch):
    pipe = io.StringIO()  # isatty() is False, as for CI logs and pipes
    monkeypatch.setattr("sys.stderr", pipe)
    bar = ProgressBar("quiet")
    for k in range(1, 11):
        bar(k, 10)
    assert pipe.getvalue() == ""
