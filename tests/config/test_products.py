"""Each config field declares the products it changes (tracegs.products); the run identity follows from it."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from hydra import compose

from tracegs.config.identity import scoped_values
from tracegs.config.schema import TraceGSConfig, register_configs
from tracegs.errors import ConfigError
from tracegs.products import STAGE1, STAGE2, declarations, reads
from tracegs.ranges import at_least
from tracegs.training.config import LossConfig

pytestmark = pytest.mark.usefixtures("hydra_context")  # tests/conftest.py


@dataclass
class LossWithUndeclaredWeight(LossConfig):
    lambda_new: float = 0.5


@dataclass
class UndeclaredFieldSchema(TraceGSConfig):
    loss: LossWithUndeclaredWeight = reads(STAGE1, factory=LossWithUndeclaredWeight)


@dataclass
class LossWithStage2Weight(LossConfig):
    lambda_new: float = reads(STAGE2, default=0.5, range=at_least(0))


@dataclass
class Stage2FieldSchema(TraceGSConfig):
    loss: LossWithStage2Weight = reads(STAGE1, factory=LossWithStage2Weight)


def test_a_field_without_a_declaration_is_refused_at_registration():
    with pytest.raises(ConfigError, match=r"^config field 'loss\.lambda_new': declares no products"):
        register_configs(UndeclaredFieldSchema)


@pytest.fixture
def stage2_field_schema():
    """The schema with one more loss weight, declared as read by Stage 2, registered for this test only."""
    register_configs(Stage2FieldSchema)
    yield
    register_configs()


def folders(*overrides: str) -> dict[str, str]:
    """Where A, Stage 1, Stage 2 (F) and F's evaluation are written under ``overrides``."""
    found = {stage: str(compose(config_name="train", overrides=[f"stage={stage}", *overrides]).run_dir)
             for stage in ("baseline", "stage1", "stage2")}
    found["evaluate"] = str(compose(config_name="evaluate", overrides=list(overrides)).evaluation.out_dir)
    return found


def test_a_field_read_by_stage2_moves_stage2_and_evaluation_only(stage2_field_schema):
    default, changed = folders(), folders("loss.lambda_new=0.9")
    assert {product for product in default if default[product] != changed[product]} == {"stage2", "evaluate"}


def test_a_field_changed_through_others_is_named_by_their_values():
    """``trainer.max_steps`` (the debug presets' budget for every stage) reaches the products through each stage's
    ``stage.max_steps`` alone: every product moves, and no identity holds the field itself."""
    declared = declarations(TraceGSConfig)
    through = {path: found.via for path, found in declared.items() if found.via}
    assert through == {"trainer.max_steps": ("stage.max_steps",)}
    assert all(declared[target].products for targets in through.values() for target in targets)
    default, budgeted = folders(), folders("trainer.max_steps=5")
    assert all(default[product] != budgeted[product] for product in default)
    assert "trainer.max_steps" not in scoped_values(compose(config_name="train", overrides=["trainer.max_steps=5"]),
                                                    "stage2")
