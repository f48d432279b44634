"""`experiment=rehearsal` is `experiment=paper` with only sizes shrunk (the CPU rehearsal of the paper scale).

Both configurations are composed, flattened to dotted keys (interpolations unresolved, so a changed
interpolation counts as a difference) and compared: every differing key must be declared in SIZE_KEYS
(tests/support/rehearsal.py) with the reason it is a size, and every iteration-based schedule must be the
paper's divided by one factor.
"""

from __future__ import annotations

from fractions import Fraction

import pytest
from hydra import compose
from omegaconf import OmegaConf
from support.rehearsal import SIZE_KEYS

ITERATION_FACTOR = Fraction(1, 100)


def flatten(node, prefix: str = "") -> dict[str, object]:
    """Dotted key -> leaf value; lists are leaves (a schedule is compared as a whole)."""
    out: dict[str, object] = {}
    for key, value in node.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, f"{dotted}."))
        else:
            out[dotted] = value
    return out


def composed(config_name: str, experiment: str) -> dict[str, object]:
    cfg = compose(config_name=config_name, overrides=[f"experiment={experiment}"])
    return flatten(OmegaConf.to_container(cfg, resolve=False))


def differing_keys(config_name: str) -> dict[str, tuple[object, object]]:
    paper, rehearsal = composed(config_name, "paper"), composed(config_name, "rehearsal")
    assert paper.keys() == rehearsal.keys()
    return {k: (paper[k], rehearsal[k]) for k in paper if paper[k] != rehearsal[k]}


@pytest.mark.parametrize("config_name", ["prepare", "train", "evaluate"])
def test_rehearsal_differs_from_paper_only_in_sizes(hydra_context, config_name):
    differing = differing_keys(config_name)
    undeclared = {k: v for k, v in differing.items() if k not in SIZE_KEYS}
    assert not undeclared, f"experiment=rehearsal differs from experiment=paper outside the size keys: {undeclared}"


def test_every_declared_size_key_is_shrunk(hydra_context):
    stale = sorted(set(SIZE_KEYS) - set(differing_keys("train")))
    assert not stale, f"declared size keys that do not differ (remove them): {stale}"


def test_iteration_schedules_are_scaled_by_one_factor(hydra_context):
    differing = differing_keys("train")
    for key, reason in SIZE_KEYS.items():
        if not reason.startswith("iteration"):
            continue
        paper, rehearsal = differing[key]
        pairs = zip(paper, rehearsal) if isinstance(paper, list) else [(paper, rehearsal)]
        for full, small in pairs:
            assert Fraction(small, full) == ITERATION_FACTOR, f"{key}: {small} is not {full} x {ITERATION_FACTOR}"
