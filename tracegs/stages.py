"""The product graph, written once: every product kind, and per trained stage what it makes and reads.

Each lookup of the graph (the artifacts a stage loads, the earlier run that made an artifact, the contents a run
record holds, the products made from a trained one, a stage's product folder) is derived from :data:`STAGES`, so
adding a product means one row here and the new stage's own module.

The module imports nothing of the project but :mod:`tracegs.modes`: the config dataclasses of every package
(:mod:`tracegs.products`) and the engines read it from below every layer.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from tracegs.modes import Mode


class Product(Mode):
    """A run kind whose folder is named by its identity (``${tracegs.run:<kind>}``)."""

    prepare = "prepare"
    baseline = "baseline"
    stage1 = "stage1"
    stage2 = "stage2"
    deploy = "deploy"
    evaluate = "evaluate"
    restore = "restore"


# The products that load the trained restorers.
DEPLOYMENT = (Product.deploy, Product.evaluate, Product.restore)


@dataclass(frozen=True)
class Stage:
    """A trained stage (``tracegs-train stage=<product>``, conf/stage/<product>.yaml): it writes ``folder`` inside
    its run folder, which later runs find as ``artifacts.<artifact>``; it loads the products of the stages in
    ``reads``; ``made_into``: the products made from it, whose identity its settings are part of
    (tracegs.products.reads); ``per_variant``: each Table 3 variant trains its own, where the stages before it
    are shared by every variant (trained with the default variant's sections)."""

    product: str
    artifact: str
    folder: str
    reads: tuple[str, ...] = ()
    made_into: tuple[str, ...] = ()
    per_variant: bool = False


@dataclass(frozen=True)
class StageTable:
    """The trained stages in training order, and ``also_loading``: the products that are no trained stage but
    load one's content (their run records hold it)."""

    stages: tuple[Stage, ...]
    also_loading: Mapping[str, tuple[str, ...]] = field(default_factory=dict)

    def names(self) -> tuple[str, ...]:
        """The trained stages' product names, in training order."""
        return tuple(stage.product for stage in self.stages)

    def stage(self, name: str) -> Stage:
        """The stage named ``name``; a name that is none is a one-line error."""
        for stage in self.stages:
            if stage.product == name:
                return stage
        raise KeyError(f"stage.name: {name!r} is no trained stage ({', '.join(self.names())})")

    def producer(self, artifact: str) -> Stage:
        """The stage whose product ``artifacts.<artifact>`` is."""
        for stage in self.stages:
            if stage.artifact == artifact:
                return stage
        raise KeyError(f"artifacts.{artifact}: no trained stage makes it")

    def stage_inputs(self, name: str) -> tuple[str, ...]:
        """The artifact keys of the earlier products the stage ``name`` loads."""
        return tuple(self.stage(earlier).artifact for earlier in self.stage(name).reads)

    def record_inputs(self, kind: str) -> tuple[str, ...]:
        """The artifact keys whose content the run record of a ``kind`` run holds (an edit recomputes it)."""
        loaded = self.stage(kind).reads if kind in self.names() else self.also_loading.get(kind, ())
        return tuple(self.stage(earlier).artifact for earlier in loaded)

    def made_from(self, products: Iterable[str]) -> frozenset[str]:
        """``products`` and every product made from them, transitively."""
        made = {stage.product: stage.made_into for stage in self.stages}
        found: set[str] = set()
        todo = list(products)
        while todo:
            product = todo.pop()
            if product not in found:
                found.add(product)
                todo.extend(made.get(product, ()))
        return frozenset(found)


STAGES = StageTable(
    stages=(
        # Variant A's restorer: the whole transformer, a diffusers folder (embedded scale; the paper loads
        # GSFixer's pretrained restorer).
        Stage(Product.baseline, "baseline_weights", "baseline_transformer", made_into=(Product.stage1,)),
        # Privileged direction alignment (main paper Sec. 3.3): the aligned adapter phi on A's weights.
        Stage(Product.stage1, "stage1_adapter", "stage1_adapter", reads=(Product.baseline,),
              made_into=(Product.stage2,)),
        # On-policy distillation (main paper Sec. 3.4): the student adapter phi_S, cloned from the Stage-1
        # adapter; the only thing deployment loads beside A's weights.
        Stage(Product.stage2, "student_adapter", "student_adapter", reads=(Product.baseline, Product.stage1),
              made_into=DEPLOYMENT, per_variant=True),
    ),
    # A cache whose pseudo-targets variant A makes reads A (tracegs.pipeline.prepare.pseudo_target_generator).
    also_loading={Product.prepare: (Product.baseline,)},
)

# The trained stages, a closed set of the ``stage.name`` field.
StageName = Mode("StageName", {str(name): str(name) for name in STAGES.names()}, module=__name__)
