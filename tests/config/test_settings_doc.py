"""The measurements behind the embedded settings live in docs/settings.md, generated from recorded runs; the config
files keep a reason per value and no measurement log."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from hydra import compose
from omegaconf import OmegaConf

from tracegs.errors import InputFileError
from tracegs.location import CONF_DIR
from tracegs.pipeline.settings_doc import HISTORY, SETTINGS, main, write_settings_document
from tracegs.provenance import describe

# What a measurement log leaves in a comment: a figure in dB, a duration, a signed difference with two decimals
# (+0.27), or a commit-hash-like token (seven or more hex characters mixing digits and letters).
MEASUREMENT = {
    "decibels": re.compile(r"\d\s*dB\b"),
    "duration": re.compile(r"\b\d+(\.\d+)?\s*(s|sec|seconds?|min|minutes?|h|hours?)\b"),
    "signed difference": re.compile(r"(?<![\w.])[+-]\d+\.\d{2}\b"),
    "commit": re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}\b"),
}
# A comment: '#' at the start of a line or after whitespace (a '#' inside a value, e.g. a URL fragment, is not one).
COMMENT = re.compile(r"(?:^|\s)#(.*)$")


def comment_measurements(text: str) -> list[tuple[int, str, str]]:
    """(line, kind, comment) of every config comment holding a measurement-like figure."""
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        match = COMMENT.search(line)
        if match:
            found += [(number, kind, match.group(1).strip()) for kind, pattern in MEASUREMENT.items()
                      if pattern.search(match.group(1))]
    return found


def test_the_measurement_check_tells_logs_from_reasons():
    log = "  #   EMA 0.99: +0.02 / +0.27 dB; took 11.5 minutes (A in 116 s) at 39e546e\n  x: 1  # 23.77 dB"
    assert {kind for _, kind, _ in comment_measurements(log)} == set(MEASUREMENT)
    reasons = ("  # Chosen on the validation scenes (docs/settings.md).\n"
               "  lpips_weights: ${paths.weights_dir}/vgg16-397923af.pth   # torchvision's VGG16 file\n"
               "  # 8k+1 frames, lr 1e-3, K = 3, 6, 9; M = 20 steps; within minutes; 24 clips x 6 conditions\n")
    assert comment_measurements(reasons) == []


def test_no_config_comment_holds_a_measurement_log():
    offending = [f"{path.relative_to(CONF_DIR)}:{line} ({kind}): {comment}"
                 for path in sorted(Path(CONF_DIR).rglob("*.yaml"))
                 for line, kind, comment in comment_measurements(path.read_text())]
    assert offending == [], "measurements belong in docs/settings.md:\n" + "\n".join(offending)


def test_every_setting_the_document_reports_is_set_where_it_says(hydra_context):
    cfg = compose(config_name="demo")
    for key, where in SETTINGS:
        assert OmegaConf.select(cfg, key, default="missing") != "missing", key
        assert key.rsplit(".", 1)[-1] in (Path(CONF_DIR).parent / where).read_text(), (key, where)
        assert "docs/settings.md" in (Path(CONF_DIR).parent / where).read_text(), where


def recorded_run(folder: Path, commit: str | None = None) -> Path:
    """A tiny run folder as tracegs-demo records it: run.json, the resolved config and one result figure."""
    folder.mkdir(parents=True)
    cfg = compose(config_name="demo")
    (folder / "config.yaml").write_text(OmegaConf.to_yaml(OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"]),
                                                          resolve=True))
    run = {**describe(0), "wall_s": 90.0, "peak_rss_gib": 0.5, "step_s": {"train stage=baseline": 42.5}}
    if commit is not None:
        run["commit"] = commit
    (folder / "run.json").write_text(json.dumps(run))
    (folder / "results.json").write_text(json.dumps({"3dgs": {"3": {"psnr": 17.25, "ssim": 0.5, "lpips": None}}}))
    return folder


def test_the_document_states_commit_machine_settings_and_figures(hydra_context, tmp_path):
    run = recorded_run(tmp_path / "seed0-run")
    output = tmp_path / "docs" / "settings.md"
    assert main([str(run), "--output", str(output)]) == 0
    document = output.read_text()
    provenance = describe(0)
    assert f"Commit {provenance['commit']}, seed 0" in document
    assert provenance["machine"]["cpu"] in document and f"{provenance['machine']['cores']} cores" in document
    assert "| train stage=baseline | 42.5 |" in document and "Wall time 1.5 min" in document
    assert "| `experiment.stage2_steps` | `200` | conf/experiment/embedded.yaml |" in document
    assert "| 3DGS, 3 views | 17.25 |" in document


def test_history_is_kept_and_a_replaced_commit_moves_into_it(hydra_context, tmp_path):
    output = tmp_path / "settings.md"
    output.write_text(f"{HISTORY}\n\nold figures, recorded in abc1234\n")
    write_settings_document([recorded_run(tmp_path / "first", commit="1111111aaaaa")], output)
    write_settings_document([recorded_run(tmp_path / "second", commit="2222222bbbbb")], output)
    current, history = output.read_text().split(HISTORY)
    assert "Commit 2222222bbbbb" in current and "1111111aaaaa" not in current
    assert "Commit 1111111aaaaa" in history and "old figures, recorded in abc1234" in history
    # the same commit regenerated replaces its section instead of piling it up
    write_settings_document([tmp_path / "second"], output)
    assert output.read_text().count("Commit 2222222bbbbb") == 1


def test_a_folder_without_a_run_record_is_one_line_and_writes_nothing(tmp_path, capsys):
    output = tmp_path / "settings.md"
    assert main([str(tmp_path), "--output", str(output)]) == 1
    assert "no run.json" in capsys.readouterr().err and not output.exists()
    with pytest.raises(InputFileError, match="run.json"):
        write_settings_document([tmp_path], output)
