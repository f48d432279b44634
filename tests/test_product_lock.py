"""One job per product folder: a lock file in the folder, one per shard; a failing job leaves nothing behind."""

from __future__ import annotations

import pytest
from filelock import FileLock, Timeout

from tracegs.errors import OutputPathError
from tracegs.pipeline.records import LOCK_FILE, product_lock


def held(path) -> bool:
    """Whether another holder has the lock at ``path`` (a second FileLock in this process cannot take it)."""
    try:
        with FileLock(path, timeout=0, is_singleton=False, thread_local=False):
            return False
    except Timeout:
        return True


def test_a_job_holds_its_folder_and_each_shard_its_own_lock(tmp_path):
    folder = tmp_path / "run"
    with product_lock(folder, "run_dir"):
        assert held(folder / LOCK_FILE)
    assert not held(folder / LOCK_FILE)
    with product_lock(folder, "evaluation.out_dir", (0, 2)), product_lock(folder, "evaluation.out_dir", (1, 2)):
        assert held(folder / f"{LOCK_FILE}.shard0of2") and held(folder / f"{LOCK_FILE}.shard1of2")
        assert not held(folder / LOCK_FILE)


def test_the_other_ranks_of_a_job_do_not_wait_for_its_lock(tmp_path, monkeypatch):
    """Rank 1 of a DDP job runs the same command as rank 0, which holds the lock: it must go on (rank 0 waits for
    it to join the process group)."""
    from lightning.fabric.utilities.rank_zero import rank_zero_only

    folder = tmp_path / "run"
    with product_lock(folder, "run_dir"):
        monkeypatch.setattr(rank_zero_only, "rank", 1)
        with product_lock(folder, "run_dir"):  # would wait forever on rank 0's lock
            assert held(folder / LOCK_FILE)


def test_a_failing_job_leaves_no_folder_or_lock_it_made(tmp_path):
    folder = tmp_path / "new" / "run"
    with pytest.raises(ValueError), product_lock(folder, "run_dir"):
        raise ValueError("bad input")
    assert not folder.exists()
    existing = tmp_path / "existing"
    (existing / ".hydra").mkdir(parents=True)
    with pytest.raises(ValueError), product_lock(existing, "run_dir"):
        raise ValueError("bad input")
    assert [p.name for p in existing.iterdir()] == [".hydra"]


def test_an_output_path_that_is_a_file_names_the_field(tmp_path):
    (tmp_path / "cache").write_text("not a folder")
    with pytest.raises(OutputPathError, match="data.prepare.cache_dir"):
        with product_lock(tmp_path / "cache", "data.prepare.cache_dir"):
            pass
