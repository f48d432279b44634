"""Every numeric config field declares its range (tracegs.ranges) beside its products, and the composed config
admits each end of it and refuses one step outside, in one line naming the field and its range. A numeric field
without a range is refused when the schema is registered."""

from __future__ import annotations

import dataclasses
import math
import sys

import pytest
from hydra import compose
from omegaconf import OmegaConf

from tracegs.config.schema import TraceGSConfig, register_configs
from tracegs.config.validate import validate, validate_ranges
from tracegs.deploy.config import RefinementConfig
from tracegs.errors import ConfigError
from tracegs.products import BASELINE, execution, reads
from tracegs.ranges import FieldRange, at_least, ranges
from tracegs.splat.config import TrajectoryConfig
from tracegs.training.config import StageConfig

DECLARED = ranges(TraceGSConfig)  # refuses, at collection, a numeric field of the schema that declares none


def _beyond(end: float, outward: float, number: type) -> float:
    """The next value past ``end`` going towards ``outward`` (one integer, or the next float)."""
    return end + (1 if outward > end else -1) if number is int else math.nextafter(end, outward)


def probes(declared: FieldRange, length: int = 1) -> list[tuple[object, bool]]:
    """(value, admitted) at each end of the field's range and one step outside it: an open end is itself outside
    (the next value in is inside), a closed one inside (the next value out is outside); a float has no infinite
    end (the largest float is inside, infinity and NaN outside). A list field gets each as a list of ``length``
    items (so that other fields' interpolations of its items still resolve), and the empty list. ``None`` is the
    type's to admit, not the range's."""
    bounds, number = declared.range, declared.number
    found = [(value, True) for value in bounds.also]
    for end, is_open, inward in ((bounds.low, bounds.low_open, math.inf), (bounds.high, bounds.high_open, -math.inf)):
        if math.isinf(end):
            if number is float:
                found += [(math.copysign(sys.float_info.max, end), True), (end, False)]
            continue
        end = number(end)
        inside = _beyond(end, inward, number) if is_open else end
        outside = end if is_open else _beyond(end, -inward, number)
        while outside in bounds.also:  # a sentinel just past the end (-1 below 0) is inside: the next one is not
            outside = _beyond(outside, -inward, number)
        found += [(inside, True), (outside, False)]
    if number is float:
        found.append((math.nan, False))
    if bounds.items:
        found = [([value] * length, admitted) for value, admitted in found] + [([], not bounds.non_empty)]
    return found


@pytest.fixture(scope="module")
def composed(hydra_context):
    """The default train config, and its fields unresolved (to put each one back after a probe)."""
    cfg = compose(config_name="train")
    return cfg, OmegaConf.to_container(cfg, resolve=False)


def given(tree: dict, field: str):
    for key in field.split("."):
        tree = tree[key]
    return tree


@pytest.mark.parametrize("field", sorted(DECLARED))
def test_each_end_of_a_range_is_admitted_and_one_step_outside_refused_naming_the_field(composed, field):
    cfg, unresolved = composed
    validate_ranges(cfg)
    try:
        original = given(unresolved, field)
        for value, admitted in probes(DECLARED[field], max(1, len(original) if isinstance(original, list) else 1)):
            OmegaConf.update(cfg, field, value, merge=False)
            if admitted:
                validate_ranges(cfg)
                continue
            with pytest.raises(ConfigError) as refused:
                validate_ranges(cfg)
            line = str(refused.value)
            assert "\n" not in line and refused.value.field == field, (value, line)
            assert line.startswith(f"config field '{field}': ") and f"must be {DECLARED[field].range}" in line
    finally:
        OmegaConf.update(cfg, field, given(unresolved, field), merge=False)


def test_every_range_has_ends_to_probe():
    """A range with no finite end, no sentinel and no list to empty would leave a field untested above: only a
    float's infinite ends (probed by the largest float and infinity) may stand in for them."""
    for field, declared in DECLARED.items():
        assert any(not admitted for _, admitted in probes(declared)), field


@pytest.mark.parametrize(("override", "field", "message"), [
    ("stage.max_steps=-1", "stage.max_steps", "-1 is out of range: must be >= 0"),
    ("seed=-3", "seed", "-3 is out of range: must be in [0, 4294967295]"),
    ("evaluation.views=[]", "evaluation.views", "[] is out of range: must be a non-empty list, each >= 2"),
    ("optimizer.lr=nan", "optimizer.lr", "nan is out of range: must be finite and > 0"),
    ("data.prepare.dense_views=[12,0,null]", "data.prepare.dense_views", "an item may be null"),
    ("trainer.max_steps=0", "trainer.max_steps", "must be >= 1 (or null)"),
])
def test_an_override_out_of_range_is_refused_in_one_line(hydra_context, override, field, message):
    with pytest.raises(ConfigError) as refused:
        validate(compose(config_name="train", overrides=["stage=stage2", override]))
    assert refused.value.field == field and message in str(refused.value)


@dataclasses.dataclass
class Unranged:
    steps: int = reads(BASELINE, default=1)


@dataclasses.dataclass
class UnrangedRoot:
    part: Unranged = execution(factory=Unranged)


@dataclasses.dataclass
class Misplaced:
    name: str = execution(default="x", range=at_least(1))


def test_a_numeric_field_without_a_range_is_refused_at_registration():
    with pytest.raises(ConfigError, match="config field 'part.steps': declares no range"):
        register_configs(UnrangedRoot)


def test_a_range_on_a_field_that_is_not_numeric_is_refused():
    with pytest.raises(ConfigError, match="config field 'name': declares the range '>= 1'"):
        ranges(Misplaced)


@pytest.mark.parametrize(("build", "field"), [
    (lambda: StageConfig(keep_checkpoints=2), "stage.keep_checkpoints"),
    (lambda: RefinementConfig(clip_batch=0).validate(), "clip_batch"),
    (lambda: RefinementConfig(repair_iters=[]).validate(), "repair_iters"),
    (lambda: RefinementConfig(trajectory=TrajectoryConfig(pitch_degrees=[])).validate(), "trajectory.pitch_degrees"),
])
def test_a_config_built_in_python_is_checked_against_the_same_ranges(build, field):
    """A section built without Hydra (an engine's caller, a benchmark) is refused by the ranges its fields declare,
    not by a second hand-written copy of them."""
    with pytest.raises(ConfigError, match=f"config field '{field}': .* is out of range"):
        build()
    assert StageConfig(keep_checkpoints=-1, ema_decay=0.0).keep_checkpoints == -1  # each end and sentinel admitted
