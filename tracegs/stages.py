"""The product graph, written once: every product kind, and per trained stage what it makes and reads, which
LightningModule trains it, and which config sections are a stage's or a variant's own.

Each lookup of the graph (the artifacts a stage loads, the earlier run that made an artifact, the contents a run
record holds, the products made from a trained one and so the fields whose values name it, a stage's product
folder, the module the runner trains) is derived from the table :func:`stage_table` returns, read when the lookup
runs, so adding a product means one row here and the new stage's own module.

The module imports nothing of the project but :mod:`tracegs.modes`: the config dataclasses of every package
(:mod:`tracegs.products`) and the engines read it from below every layer. A row names its LightningModule by
import path; the runner (tracegs.training.run) imports it.
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
    """A trained stage (``tracegs-train stage=<product>``, conf/stage/<product>.yaml): the LightningModule
    ``module`` (``package.module:Class``, a tracegs.training.module.RestorerTrainingModule) trains it and writes
    ``folder`` inside its run folder, which later runs find as ``artifacts.<artifact>``; it loads the products of
    the stages in ``reads``; ``made_into``: the products made from it, whose identity its settings are part of
    (tracegs.products.reads); ``per_variant``: each Table 3 variant trains its own (a variant that trains no
    student, ``ablation.train_stage2: false``, trains none), where the stages before it are shared by every
    variant (trained with the default variant's sections, :attr:`StageTable.shared_by_variants`)."""

    product: str
    artifact: str
    folder: str
    module: str
    reads: tuple[str, ...] = ()
    made_into: tuple[str, ...] = ()
    per_variant: bool = False


# A table is compared and hashed by identity: caches of what it derives (tracegs.products.declarations) are kept
# per table, and a copy of it (a test's) is another table.
@dataclass(frozen=True, eq=False)
class StageTable:
    """The trained stages in training order, and:

    - ``also_loading``: the products that are no trained stage but load one's content (their run records hold it);
    - ``deployed``: the trained products a deployment loads (its restorer);
    - ``stage_sections``: the config sections a stage's settings live in, wholly its own: its option
      (conf/stage/<product>.yaml) sets them, and a lookup of another stage takes that stage's option for them;
      ``option_also_sets``: the sections whose keys the options set beside them;
    - ``variant_sections``: the sections a Table 3 variant sets (conf/ablation/<name>.yaml and the options it
      selects); ``shared_by_variants``: those a stage shared by the variants (not ``per_variant``) is looked up
      with at the default variant's values.
    """

    stages: tuple[Stage, ...]
    also_loading: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    deployed: tuple[str, ...] = ()
    stage_sections: tuple[str, ...] = ()
    option_also_sets: tuple[str, ...] = ()
    variant_sections: tuple[str, ...] = ()
    shared_by_variants: tuple[str, ...] = ()

    def names(self) -> tuple[str, ...]:
        """The trained stages' product names, in training order."""
        return tuple(stage.product for stage in self.stages)

    def products(self) -> frozenset[str]:
        """Every product kind: the :class:`Product` members and the trained stages."""
        return frozenset(Product) | frozenset(self.names())

    def product(self, kind: str, field: str) -> str:
        """``kind`` as a product kind (a :class:`Product` member where it is one); another is a one-line error naming
        ``field`` and the kinds."""
        if kind in Product._value2member_map_:
            return Product(kind)
        if kind in self.names():
            return self.stage(kind).product
        raise ValueError(f"{field} must be one of {sorted(self.products())}, got {kind!r}")

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

    def artifacts(self, names: Iterable[str]) -> tuple[str, ...]:
        """The artifact keys of the stages ``names``."""
        return tuple(self.stage(name).artifact for name in names)

    def stage_inputs(self, name: str) -> tuple[str, ...]:
        """The artifact keys of the earlier products the stage ``name`` loads."""
        return self.artifacts(self.stage(name).reads)

    def record_inputs(self, kind: str) -> tuple[str, ...]:
        """The artifact keys whose content the run record of a ``kind`` run holds (an edit recomputes it)."""
        return self.artifacts(self.stage(kind).reads if kind in self.names() else self.also_loading.get(kind, ()))

    def deployed_artifacts(self) -> tuple[str, ...]:
        """The artifact keys a deployment loads."""
        return self.artifacts(self.deployed)

    def per_variant(self) -> Stage:
        """The stage each Table 3 variant trains its own of."""
        (stage,) = (stage for stage in self.stages if stage.per_variant)
        return stage

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
        Stage(Product.baseline, "baseline_weights", "baseline_transformer",
              "tracegs.training.baseline:BaselineRestorerModule", made_into=(Product.stage1,)),
        # Privileged direction alignment (main paper Sec. 3.3): the aligned adapter phi on A's weights.
        Stage(Product.stage1, "stage1_adapter", "stage1_adapter", "tracegs.training.stage1:Stage1AlignmentModule",
              reads=(Product.baseline,), made_into=(Product.stage2,)),
        # On-policy distillation (main paper Sec. 3.4): the student adapter phi_S, cloned from the Stage-1
        # adapter; the only thing deployment loads beside A's weights.
        Stage(Product.stage2, "student_adapter", "student_adapter",
              "tracegs.training.stage2:Stage2DistillationModule", reads=(Product.baseline, Product.stage1),
              made_into=DEPLOYMENT, per_variant=True),
    ),
    # A cache whose pseudo-targets variant A makes reads A (tracegs.pipeline.prepare.pseudo_target_generator).
    also_loading={Product.prepare: (Product.baseline,)},
    # The deployed restorer: the student adapter on A's weights (main paper Sec. 3.4).
    deployed=(Product.baseline, Product.stage2),
    # conf/stage/<product>.yaml sets a stage's budget and rates (stage, optimizer) and its clips per scene.
    stage_sections=("stage", "optimizer"),
    option_also_sets=("data.datamodule",),
    # A variant's own file and the teacher, policy and loss options it selects. What A and Stage 1 read of a
    # variant is the default variant's (every variant clones their products); its loss differs between variants
    # only in what Stage 2 reads, and stays the command's own.
    variant_sections=("ablation", "teacher", "policy", "loss"),
    shared_by_variants=("ablation", "teacher", "policy"),
)


def stage_table() -> StageTable:
    """The product graph every lookup reads, when it runs (so a copy with a stage added, a test's, is read by
    all of them alike)."""
    return STAGES

# The trained stages, a closed set of the ``stage.name`` field.
StageName = Mode("StageName", {str(name): str(name) for name in STAGES.names()}, module=__name__)
