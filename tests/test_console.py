"""Plain progress lines when stdout is not a terminal, and what a run shows also reaching its log files."""

from __future__ import annotations

import logging

import pytest

from tracegs.console import PlainProgress, seconds_left, show


def test_plain_progress_logs_at_its_interval_and_at_the_end(caplog, monkeypatch):
    monkeypatch.setattr("sys.stdout.isatty", lambda: False)
    with caplog.at_level(logging.INFO, logger="tracegs"):
        progress = PlainProgress("fits", total=3, every_s=3600.0)
        for done in (1, 2, 3):
            progress.update(done)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and lines[0].startswith("fits: 3/3, ")


@pytest.mark.parametrize(("done", "total", "elapsed", "parallel", "left"), [
    (1, 4, 10.0, 1, 30.0),  # one at a time: 10 s an item, three left
    (2, 4, 10.0, 2, 10.0),  # two at a time, 10 s each: the last two take one more round, not two
    (1, 4, 10.0, 2, 40.0),  # one item in 10 s on two workers: 20 s an item as measured, two rounds left
    (3, 4, 15.0, 2, 10.0),  # the last one runs beside an idle worker: one round
    (0, 4, 5.0, 2, float("nan")),
])
def test_time_left_counts_the_items_that_run_at_once(done, total, elapsed, parallel, left):
    assert seconds_left(done, total, elapsed, parallel) == pytest.approx(left, nan_ok=True)


def test_a_resumed_run_measures_only_the_steps_it_ran(caplog, monkeypatch):
    monkeypatch.setattr("sys.stdout.isatty", lambda: False)
    clock = iter([0.0, 10.0])
    monkeypatch.setattr("tracegs.console.time.monotonic", lambda: next(clock))
    with caplog.at_level(logging.INFO, logger="tracegs"):
        PlainProgress("train", total=100, every_s=0.0, first=80).update(90)  # 10 steps in 10 s, 10 left
    assert caplog.records[0].getMessage().endswith("~10 s left")


def test_shown_text_reaches_the_log_file(tmp_path, capsys):
    handler = logging.FileHandler(tmp_path / "run.log")
    logging.getLogger().addHandler(handler)
    try:
        show("| Method | PSNR 3 |")
    finally:
        logging.getLogger().removeHandler(handler)
        handler.close()
    assert capsys.readouterr().out == "| Method | PSNR 3 |\n"
    assert "| Method | PSNR 3 |" in (tmp_path / "run.log").read_text()
