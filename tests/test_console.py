"""Plain progress lines when stdout is not a terminal, and what a run shows also reaching its log files."""

from __future__ import annotations

import logging

from tracegs.console import PlainProgress, show


def test_plain_progress_logs_at_its_interval_and_at_the_end(caplog, monkeypatch):
    monkeypatch.setattr("sys.stdout.isatty", lambda: False)
    with caplog.at_level(logging.INFO, logger="tracegs"):
        progress = PlainProgress("fits", total=3, every_s=3600.0)
        for done in (1, 2, 3):
            progress.update(done)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and lines[0].startswith("fits: 3/3, ")


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
