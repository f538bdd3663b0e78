"""A finding about a store or an input: where, and what is wrong there.

Every check of the format returns a list of these (empty: nothing wrong), never a formatted line.
The readers raise the first one (:func:`raise_first`); ``validate`` lists them all, one a line.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar, Sequence

from sonarset.errors import FormatError, SonarSetError


@dataclass(frozen=True)
class Problem:
    #: The node (a store, ``<store>/<run>``, ``<store>/<run>/<array>``) or the input field the
    #: problem is in; empty while the check that found it does not know (its caller places it, :meth:`at`).
    where: str
    message: str
    #: The first frame the problem concerns, where it concerns one: a reader names its chunk.
    frame: int | None = None
    #: Whether a reader refuses what this problem is about (some findings only ``validate`` acts on).
    refused_by_readers: ClassVar[bool] = True

    def __str__(self) -> str:
        return f"{self.where}: {self.message}" if self.where else self.message

    def at(self, where: str) -> "Problem":
        """The problem placed under ``where``: an array's ``images`` found in run ``<store>/r``
        becomes ``<store>/r/images``."""
        return replace(self, where=f"{where}/{self.where}" if self.where else where)


def raise_first(problems: Sequence[Problem], error: type[SonarSetError] = FormatError) -> None:
    """Raise ``error`` with the first of ``problems``, if there is one: what a reader does."""
    if problems:
        raise error(str(problems[0]))


def pydantic_problems(exc: Exception, prefix: str = "") -> list[Problem]:
    """One problem per pydantic error, naming the field: 'grid.n_range: Input should be greater
    than or equal to 1' (``prefix`` before the field: where the document sits in its file)."""
    errors = getattr(exc, "errors", None)
    if not callable(errors):
        return [Problem("", f"{prefix}{exc}")]
    out = []
    for err in errors():
        loc = ".".join(str(p) for p in err.get("loc", ()))
        field = f"{prefix}{loc}" if loc else prefix.rstrip(".")
        msg = err.get("msg", "invalid")
        out.append(Problem("", f"{field}: {msg}" if field else msg))
    return out
