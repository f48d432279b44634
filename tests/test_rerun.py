"""A rerun never changes a product: ``tracegs-demo`` run again on its root, or on a copy of the root elsewhere
reached through another spelling, trains nothing and leaves every product byte for byte; two identical jobs at
once do the work once; a command refused by validation writes nothing.

Products are every file under the root except logs, Hydra's own records and the lock files: the demo's
``run.json`` and ``tables.md`` hold the timings of the run that wrote them, and ``config.yaml`` the resolved
paths of the last command (they are records of a command, not products).
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import sys
from pathlib import Path

import pytest
from support.read_only import read_only_view
from support.tasks import SMALLEST

from tracegs.pipeline.records import LOCK_FILE, RUN_RECORD

# The averaged baseline must train more than one step, or its average equals its last weights.
DEMO = (*(o for o in SMALLEST if not o.startswith("experiment.baseline_steps")), "experiment.baseline_steps=3")
RECORDS_OF_A_COMMAND = {"run.json", "tables.md", "config.yaml", LOCK_FILE}


def product_sums(root: Path) -> dict[str, str]:
    """SHA-256 of every product file under ``root``, by path relative to it."""
    sums = {}
    for path in sorted(root.rglob("*")):
        relative = path.relative_to(root)
        parts = set(relative.parts)
        if (not path.is_file() or path.name in RECORDS_OF_A_COMMAND or path.suffix == ".log"
                or path.name.startswith(".") or parts & {".hydra", "csv", "tensorboard"}):
            continue
        sums[relative.as_posix()] = hashlib.sha256(path.read_bytes()).hexdigest()
    return sums


def trained_versions(root: Path) -> int:
    """Training starts under ``root``: each start of a fit writes one CSV log version."""
    return len(list(root.rglob("csv/version_*")))


def run_demo(entry_point, root: Path, spelled: str):
    result = entry_point("demo", [f"paths.root_dir={spelled}", *DEMO], root)
    assert result.returncode == 0, result.stderr[-3000:]
    return result


@pytest.fixture(scope="module")
def finished(tmp_path_factory, entry_point) -> tuple[Path, dict[str, str], int]:
    """(root, product sums, training starts) of one finished smallest-size demo."""
    root = tmp_path_factory.mktemp("rerun") / "root"
    root.mkdir()
    run_demo(entry_point, root, str(root))
    return root, product_sums(root), trained_versions(root)


def said_nothing_to_do(result) -> set[str]:
    return set(re.findall(r"\] - (\w+): \S+ already holds this run's product", result.stdout + result.stderr))


def every_file(root: Path) -> dict[str, bytes]:
    """The bytes of every file under ``root``, records and logs included, by path relative to it."""
    return {path.relative_to(root).as_posix(): path.read_bytes() for path in sorted(root.rglob("*")) if path.is_file()}


@pytest.mark.slow
def test_a_second_demo_changes_no_byte_and_trains_nothing(finished, entry_point):
    root, sums, versions = finished
    before = every_file(root)
    again = run_demo(entry_point, root, str(root))
    assert product_sums(root) == sums
    assert trained_versions(root) == versions
    assert said_nothing_to_do(again) == {"baseline", "stage1", "stage2"}
    assert not list(root.rglob("*-v1.ckpt"))
    # The record of how the products were made (run.json, tables.md, the log) stays the first run's; the held-out
    # clips are not scored again.
    after = every_file(root)
    assert sorted(after) == sorted(before) and [name for name in before if after[name] != before[name]] == []
    assert "held-out clip quality: made from the same clips, seed and restorers, kept" in again.stdout
    assert "every product was already made" in again.stdout


def outputs_and_data(root: Path) -> dict[str, bytes]:
    """:func:`every_file` under the root's ``outputs/`` and ``data/`` (Hydra's records and the logs included)."""
    return {name: data for name, data in every_file(root).items() if name.split("/")[0] in ("outputs", "data")}


@pytest.mark.slow
def test_a_copied_root_spelled_relatively_is_the_same_run(finished, entry_point, tmp_path):
    """The README's ``tracegs-demo paths.root_dir=...`` on a ``make demo`` root, after the root was copied, changes
    no byte under ``outputs/`` and ``data/``, Hydra's records of the command included (they would name the new
    paths); a root finished before its folder had a ``report.html`` gets the page the first run wrote, byte for
    byte."""
    root, sums, versions = finished
    copy = tmp_path / "copied"
    shutil.copytree(root, copy)
    before = outputs_and_data(copy)
    assert any("/.hydra/" in name for name in before)  # the first run wrote its records
    (page,) = copy.rglob("demo/*/report.html")
    page.unlink()
    again = run_demo(entry_point, copy, ".")
    assert product_sums(copy) == sums
    assert trained_versions(copy) == versions
    assert said_nothing_to_do(again) == {"baseline", "stage1", "stage2"}
    after = outputs_and_data(copy)
    assert sorted(after) == sorted(before) and [name for name in before if after[name] != before[name]] == []


@pytest.mark.slow
def test_a_finished_root_on_a_read_only_file_system_reruns_and_refuses_new_work_in_one_line(
        finished, entry_point, tmp_path):
    """A second demo on a read-only copy of a finished root finds every product finished and succeeds (no run
    record, log or lock to write); a command with new work refuses in one line naming the folder."""
    root, sums, _ = finished
    copy = tmp_path / "copied"
    shutil.copytree(root, copy)
    before = every_file(copy)
    with read_only_view(copy, tmp_path / "view") as view:
        again = entry_point("demo", [f"paths.root_dir={view}", *DEMO], tmp_path)
        assert again.returncode == 0, again.stderr[-3000:]
        assert "every product was already made" in again.stdout
        new = entry_point("train", [f"paths.root_dir={view}", *DEMO, "stage=stage1", "experiment.stage1_steps=2"],
                          tmp_path)
        assert new.returncode == 2, new.stderr[-2000:]
        (line,) = new.stderr_lines()
        assert "Read-only file system" in line and str(view) in line
    assert every_file(copy) == before


@pytest.mark.slow
def test_two_identical_jobs_at_once_do_the_work_once(finished, forked, tmp_path):
    """A second identical job waits for the first one's lock, then reuses its product."""
    root = finished[0]
    args = [f"paths.root_dir={root}", *DEMO, "stage=stage1", "experiment.stage1_steps=2"]

    def job() -> None:
        from hydra.core.global_hydra import GlobalHydra

        from tracegs.cli import train

        os.chdir(root)
        GlobalHydra.instance().clear()
        sys.argv = ["tracegs-train", *args]
        train.main()

    before = trained_versions(root)
    processes = [forked(job, tmp_path / f"{n}.out", tmp_path / f"{n}.err") for n in range(2)]
    for process in processes:
        process.join()
    codes = [process.exitcode for process in processes]
    logs = [(tmp_path / f"{n}.out").read_text() + (tmp_path / f"{n}.err").read_text() for n in range(2)]
    assert codes == [0, 0], logs
    assert trained_versions(root) == before + 1
    assert sum("already holds this run's product" in log for log in logs) == 1
    assert not list(root.rglob("*-v1.ckpt"))


REFUSED = [
    pytest.param("train", ["stage=stage1", "+stage.max_step=3"], "stage.max_step", id="misspelt-plus-key"),
    pytest.param("train", ["--cfg", "job", "+stage.max_step=3"], "stage.max_step", id="cfg-job-misspelt-plus-key"),
    pytest.param("demo", ["data.synthetic.test_seeds=[0]", "data.synthetic.train_seeds=[0]"],
                 "data.synthetic.test_seeds", id="cross-field"),
    pytest.param("evaluate", ["evaluation.held_out_cache=/tmp/x/seed0,student_views=_3_-c477b8e1"],
                 "quote", id="unquoted-path"),
    pytest.param("restore", ["capture.path=/data/a,b"], "quote", id="unquoted-capture-path"),
    # Values out of their fields' ranges (tracegs.ranges): -1 steps would train until killed, a negative seed stops
    # in numpy, no view count evaluates nothing, a NaN learning rate poisons the first step.
    pytest.param("train", ["stage=stage2", "stage.max_steps=-1"], "config field 'stage.max_steps'", id="steps"),
    pytest.param("prepare", ["seed=-3"], "config field 'seed'", id="seed"),
    pytest.param("evaluate", ["evaluation.views=[]"], "config field 'evaluation.views'", id="no-views"),
    pytest.param("train", ["optimizer.lr=nan"], "config field 'optimizer.lr'", id="nan-lr"),
]


@pytest.mark.parametrize(("app", "args", "named"), REFUSED)
def test_a_refused_command_writes_nothing(entry_point, tmp_path, app, args, named):
    root = tmp_path / "root"
    root.mkdir()
    result = entry_point(app, [f"paths.root_dir={root}", *args], tmp_path)
    assert result.returncode == 2, result.stderr[-2000:]
    (line,) = result.stderr_lines()
    assert line.startswith(f"tracegs-{app}: error:") and named in line
    assert not list(root.rglob("*")) and sorted(p.name for p in tmp_path.iterdir()) == ["root"]
    assert "job:" not in result.stdout and "task:" not in result.stdout  # --cfg job printed nothing


def test_an_evaluation_folder_of_another_run_is_refused_before_any_weights_load(entry_point, tmp_path):
    """Nothing is trained under this root, so loading the restorers would fail: the refusal comes first."""
    root = tmp_path / "root"
    other = root / "other"
    other.mkdir(parents=True)
    (other / RUN_RECORD).write_text('{"seed": 99}')
    result = entry_point("evaluate", [f"paths.root_dir={root}", f"evaluation.out_dir={other}"], tmp_path)
    assert result.returncode == 2, result.stderr[-2000:]
    (line,) = result.stderr_lines()
    assert "holds a run made with other settings" in line and str(other) in line
    assert (other / RUN_RECORD).read_text() == '{"seed": 99}'
