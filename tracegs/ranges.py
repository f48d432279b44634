"""The range of every numeric config field, declared next to the field with its products (tracegs.products).

A number outside what its code can use fails late and far from the field: ``stage.max_steps=-1`` reads to
Lightning as "no limit" and trains until killed, ``seed=-3`` stops in numpy with a message naming no field, a
learning rate of NaN poisons the first step. So every ``int`` or ``float`` field (or list of them) states the
values it admits, and the composed config is checked against them before anything is written:

- :func:`at_least`, :func:`within`, :func:`positive`: an interval of finite numbers (never NaN or infinite);
- ``also``: values outside it that mean something (each documented at its field, e.g. ``-1``: every core);
- :func:`each`: a list whose every item is in a range, not empty unless said;
- ``None`` is admitted where the field's type is optional (its comment says what it means).

A range is metadata of the field, never part of its value, so no run identity reads it. The module imports nothing
of the project but :mod:`tracegs.errors`, so every package's config dataclasses use it.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from functools import cache
from typing import Any

from tracegs.errors import ConfigError

_KEY = "tracegs.range"


@dataclasses.dataclass(frozen=True)
class Range:
    """Finite numbers from ``low`` to ``high`` (an end excluded when open), or one of ``also``; ``items``: the
    field is a list and each item must be in the range (``non_empty``: at least one)."""

    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = False
    also: tuple[float, ...] = ()
    items: bool = False
    non_empty: bool = False
    why: str = ""  # said with a refusal, where the bound is not plain from the field's name

    def admits_number(self, value: Any) -> bool:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        if value in self.also:
            return True
        if not math.isfinite(value):
            return False
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def admits(self, value: Any) -> bool:
        """Whether ``value`` (a number, or a list of them for an ``items`` range) is in the range."""
        if not self.items:
            return self.admits_number(value)
        return (isinstance(value, (list, tuple)) and (bool(value) or not self.non_empty)
                and all(self.admits_number(item) for item in value))

    def number_text(self) -> str:
        if self.low == -math.inf and self.high == math.inf:
            text = "finite"
        elif self.low == 0 and self.low_open and self.high == math.inf:
            text = "finite and > 0"
        elif self.high == math.inf:
            text = f"{'>' if self.low_open else '>='} {_number(self.low)}"
        elif self.low == -math.inf:
            text = f"{'<' if self.high_open else '<='} {_number(self.high)}"
        else:
            text = (f"in {'(' if self.low_open else '['}{_number(self.low)}, {_number(self.high)}"
                    f"{')' if self.high_open else ']'}")
        return text + "".join(f" or {_number(value)}" for value in self.also)

    def __str__(self) -> str:
        text = self.number_text() if not self.items else \
            f"{'a non-empty' if self.non_empty else 'a'} list, each {self.number_text()}"
        return text + (f" ({self.why})" if self.why else "")


def _number(value: float) -> str:
    return str(int(value)) if float(value).is_integer() and abs(value) < 1e16 else repr(value)


def at_least(low: float, *also: float, why: str = "") -> Range:
    """``low`` or more (``also``: values below that mean something; ``why``: the reason for ``low``)."""
    return Range(low=low, also=also, why=why)


def within(low: float, high: float, *also: float, low_open: bool = False, high_open: bool = False) -> Range:
    """From ``low`` to ``high``, each end included unless open."""
    return Range(low=low, high=high, low_open=low_open, high_open=high_open, also=also)


def positive() -> Range:
    """Finite and above 0 (a learning rate, a scale, an epsilon)."""
    return Range(low=0, low_open=True)


# Any finite number (a coordinate, an angle, the mean of a distribution).
FINITE = Range()
# Seeds: what numpy's and Lightning's generators accept (numpy: 0 to 2^32 - 1).
SEED = within(0, 2**32 - 1)


def each(item: Range, non_empty: bool = True) -> Range:
    """A list whose every item is in ``item``; not empty unless ``non_empty`` is False."""
    return dataclasses.replace(item, items=True, non_empty=non_empty)


def metadata(declared: Range | None) -> dict[str, Range]:
    """The field metadata holding ``declared`` (none without a range)."""
    return {} if declared is None else {_KEY: declared}


def _optional(hint: Any) -> tuple[Any, bool]:
    """(the type without ``None``, whether ``None`` was admitted)."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType) and type(None) in args:
        (hint,) = [arg for arg in args if arg is not type(None)]
        return hint, True
    return hint, False


def _numeric(hint: Any) -> tuple[type | None, bool, bool, bool]:
    """(``int`` or ``float``, else None; a list; optional; optional items) for a field's type: a number or a list
    of them, each optional or not."""
    hint, optional = _optional(hint)
    listed = typing.get_origin(hint) is list
    item, optional_items = _optional(typing.get_args(hint)[0]) if listed else (hint, False)
    return (item if item in (int, float) else None), listed, optional, optional_items


@dataclasses.dataclass(frozen=True)
class FieldRange:
    """The declared range of one numeric field of type ``number`` (``int`` or ``float``, or a list of them);
    ``optional``: its type admits ``None``, ``optional_items``: so does each item of its list."""

    range: Range
    number: type
    optional: bool = False
    optional_items: bool = False

    def admits(self, value: Any) -> bool:
        if value is None:
            return self.optional
        if self.optional_items:
            value = [item for item in value if item is not None]
        return self.range.admits(value)

    def problem(self, value: Any) -> str | None:
        """Why ``value`` is not admitted, or None."""
        if self.admits(value):
            return None
        nulls = " (or null)" if self.optional else " (an item may be null)" if self.optional_items else ""
        return f"{value!r} is out of range: must be {self.range}{nulls}"


@cache
def ranges(schema: type) -> dict[str, FieldRange]:
    """The range of every numeric field under the config dataclass ``schema``, by dotted path. Refuses a numeric
    field that declares none, and a range on a field that is not numeric (or whose list-ness differs)."""
    found: dict[str, FieldRange] = {}

    def visit(cls: type, prefix: str) -> None:
        hints = typing.get_type_hints(cls)
        for field in dataclasses.fields(cls):
            path, hint = f"{prefix}{field.name}", hints[field.name]
            if dataclasses.is_dataclass(hint):
                visit(hint, f"{path}.")
                continue
            number, listed, optional, optional_items = _numeric(hint)
            declared = field.metadata.get(_KEY)
            if number is not None and declared is None:
                raise ConfigError(path, "declares no range: give its product declaration a range=... "
                                        "(tracegs.ranges: at_least, within, positive, each, SEED, FINITE)")
            if declared is not None and (number is None or declared.items != listed):
                raise ConfigError(path, f"declares the range '{declared}', but its type is {hint}")
            if number is not None:
                found[path] = FieldRange(declared, number, optional, optional_items)

    visit(schema, "")
    return found


def _interpolation(value: Any) -> bool:
    """Whether ``value`` (or an item of it) is an OmegaConf interpolation, as in the schema's own defaults."""
    items = value if isinstance(value, (list, tuple)) else [value]
    return any(isinstance(item, str) and "${" in item for item in items)


def check_ranges(config: Any, section: str = "") -> None:
    """Refuse a field of the config dataclass instance ``config`` whose value is outside its declared range (its
    own fields; each nested section checks its own), naming it under ``section`` (e.g. ``stage``): the same check
    the composed config passes, for a config built in Python. An interpolation is left to that check, which sees
    the value it resolves to."""
    for path, declared in ranges(type(config)).items():
        value = getattr(config, path, None)
        if "." not in path and not _interpolation(value):
            problem = declared.problem(value)
            if problem is not None:
                raise ConfigError(f"{section}.{path}" if section else path, problem)
