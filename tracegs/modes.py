"""The base of every closed set of choices in a config (a mode): an Enum OmegaConf checks at composition.

It imports nothing of the project, so every package's config dataclasses declare their modes with it
without depending on ``tracegs.config`` (whose schema imports those packages).
"""

from __future__ import annotations

from enum import Enum


class Mode(str, Enum):
    """A closed set of choices: a value outside it fails at composition, naming the field. OmegaConf
    matches a YAML value to a member's name, so each member is named by its value; the member reads as
    its value, also inside interpolations such as ``job_name: ${task}-${report.kind}``."""

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)

    @classmethod
    def parse(cls, value, field: str):
        """``value`` as a member, for callers that build configs or modules without Hydra; a value outside the
        set is a one-line error naming ``field`` and the choices."""
        try:
            return cls(value)
        except ValueError:
            raise ValueError(f"{field} must be one of {[member.value for member in cls]}, got {value!r}") from None
