"""Which products a config field changes, declared next to the field.

A product is what a run writes into a folder named by its identity (tracegs.config.identity): the paired-clip
cache (``prepare``), variant A's restorer (``baseline``), the Stage-1 adapter (``stage1``), a Stage-2 student
(``stage2``), and the deployments, evaluations and restorations of a capture that load the restorers
(``deploy``, ``evaluate``, ``restore``). Every field of a config dataclass says which of them it changes:

- ``reads(*products)``: those products and every product made from them. A trained restorer is loaded by
  the products after it (Stage 1 trains on A's weights, Stage 2 clones the Stage-1 adapter, deployment loads
  the students), and a product's folder is named before the products it loads are located, so their
  settings are its settings too: ``reads(STAGE2)`` changes Stage 2 and deployment, evaluation and
  restoration, never A or Stage 1. A cache is no product's input in this sense: a trained restorer reads the
  data settings it depends on itself (``reads(PREPARE, BASELINE)``).
- ``execution()``: no product; how or where a run executes (paths, workers, logging, shards, checkpoint
  cadence) or what a command does with the products (reports, tracegs-replicate's plan, Table 3's layout).
- ``via(*fields)``: a setting other fields interpolate and that changes products only through them (a debug
  preset's step budget reaches each stage's ``stage.max_steps``): their values are in the identity, it is not.
- ``handed_in(*products)``: an input given by path instead of located (its default interpolates the located
  product, whose settings are already named); given, those products read its content, never its path.

A field holding a config dataclass declares the products of its whole section, and each field inside changes
only the products both it and its section name: a dataclass used at two places (a trajectory for prepare and
for deployment, a 3DGS fit, captions) declares its fields ``reads(EVERY)``. The run identity, the clip
settings of a cache and the fingerprint of an evaluation unit all derive from these declarations.

Every numeric field also states its range beside its declaration (``range=``, tracegs.ranges).

The products, and which are made from which, are the product graph's (:mod:`tracegs.stages`), read when the
declarations are (:func:`declarations`): a field keeps the products it names, and the products made from them are
the table's of the moment. The module
imports nothing of the project but :mod:`tracegs.stages`, :mod:`tracegs.ranges` and :mod:`tracegs.errors`, so
every package's config dataclasses use it without depending on ``tracegs.config`` (whose schema imports those
packages).
"""

from __future__ import annotations

import dataclasses
import typing
from functools import cache
from typing import Any

from tracegs.errors import ConfigError
from tracegs.ranges import Range, metadata
from tracegs.stages import DEPLOYMENT as DEPLOYMENT
from tracegs.stages import Product, StageTable, stage_table

PREPARE, BASELINE, STAGE1, STAGE2 = Product.prepare, Product.baseline, Product.stage1, Product.stage2
DEPLOY, EVALUATE, RESTORE = Product.deploy, Product.evaluate, Product.restore
# Every product: for the fields of a dataclass used at several places, which change what their section changes.
EVERY = tuple(Product)

_KEY = "tracegs.products"


@dataclasses.dataclass(frozen=True)
class Declaration:
    """What one field changes: ``products``, as the field names them (:meth:`changes`: the products made from
    them too; :func:`declarations`: those, narrowed to its sections'); ``split``: the split whose scenes it names,
    which a cache of another split does not read; ``content``: for an input handed in by path, the files that
    stand for its content (none: all of it); ``via``: the fields (dotted paths from the root) that interpolate it
    and through which alone it changes products."""

    products: frozenset[str]
    split: str | None = None
    content: tuple[str, ...] | None = None
    via: tuple[str, ...] = ()

    def changes(self) -> frozenset[str]:
        """The products the field changes: those it names and every product made from them (the stage table's)."""
        return stage_table().made_from(self.products)


def _flat(products: tuple[Product | tuple[Product, ...], ...]) -> list[Product]:
    return [p for item in products for p in (item if isinstance(item, tuple) else (item,))]


def _field(declaration: Declaration, default: Any, factory: Any, declared_range: Range | None) -> Any:
    # The range is metadata beside the declaration, never part of it: no identity reads it (tracegs.ranges).
    fields = {_KEY: declaration, **metadata(declared_range)}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=fields)
    return dataclasses.field(default=default, metadata=fields)


def reads(*products: Product | tuple[Product, ...], default: Any = dataclasses.MISSING, factory: Any = None,
          split: str | None = None, range: Range | None = None) -> Any:
    """A field that changes ``products`` and every product made from them; ``split``: a scene list of that split
    (a cache of another split does not read it). ``factory`` builds a mutable default; ``range``: the values a
    numeric field admits (tracegs.ranges), as for every declaration below."""
    return _field(Declaration(frozenset(Product(p) for p in _flat(products)), split=split), default, factory, range)


def execution(default: Any = dataclasses.MISSING, factory: Any = None, range: Range | None = None) -> Any:
    """A field that changes no product."""
    return _field(Declaration(frozenset()), default, factory, range)


def via(*fields: str, default: Any = dataclasses.MISSING, factory: Any = None,
        range: Range | None = None) -> Any:
    """A field that changes products only through ``fields`` (dotted paths from the root), which interpolate it:
    their values name the products it changes, so no identity reads it a second time."""
    return _field(Declaration(frozenset(), via=fields), default, factory, range)


def handed_in(*products: Product, content: tuple[str, ...] = (), default: Any = dataclasses.MISSING) -> Any:
    """An input given by path: ``products`` (and those made from them) read what ``content`` names inside it
    (none: all of it)."""
    return _field(Declaration(frozenset(Product(p) for p in products), content=content), default, None, None)


def declaration(field: dataclasses.Field, where: str) -> Declaration:
    """The declaration of ``field`` (at dotted ``where``); a field without one is refused."""
    found = field.metadata.get(_KEY)
    if found is None:
        raise ConfigError(where, "declares no products: give it reads(...), execution() or handed_in(...) "
                                 "(tracegs.products)")
    return found


def declarations(schema: type) -> dict[str, Declaration]:
    """Every field under the config dataclass ``schema`` by dotted path, its products the ones it changes
    (:meth:`Declaration.changes`) narrowed to its sections'. Refuses a field without a declaration."""
    return _declarations(schema, stage_table())


@cache
def _declarations(schema: type, table: StageTable) -> dict[str, Declaration]:
    found: dict[str, Declaration] = {}

    def visit(cls: type, prefix: str, products: frozenset[str]) -> None:
        hints = typing.get_type_hints(cls)
        for field in dataclasses.fields(cls):
            path = f"{prefix}{field.name}"
            own = declaration(field, path)
            found[path] = dataclasses.replace(own, products=table.made_from(own.products) & products)
            if dataclasses.is_dataclass(hints[field.name]):
                visit(hints[field.name], f"{path}.", found[path].products)

    visit(schema, "", table.products())
    return found


def read_values(section: Any, product: Product) -> dict[str, Any]:
    """``dataclasses.asdict(section)`` less the fields ``product`` does not read (inputs handed in included:
    they are known by content, not by value)."""
    values = {}
    for field in dataclasses.fields(section):
        own = declaration(field, field.name)
        if product in own.changes() and own.content is None:
            value = getattr(section, field.name)
            values[field.name] = read_values(value, product) if dataclasses.is_dataclass(value) else value
    return values


def blank_unread(section: Any, product: Product) -> Any:
    """``section`` with each field ``product`` does not read set to ``""``: the same whatever its value, in a
    digest whose earlier records hold the field."""
    blanked = {}
    for field in dataclasses.fields(section):
        value = getattr(section, field.name)
        if product not in declaration(field, field.name).changes():
            blanked[field.name] = ""
        elif dataclasses.is_dataclass(value):
            blanked[field.name] = blank_unread(value, product)
    return dataclasses.replace(section, **blanked)
