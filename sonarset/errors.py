"""Exceptions raised for bad input; the CLI turns them into one-line messages."""

from __future__ import annotations


class SonarSetError(Exception):
    """An error caused by the user's input (a file, a store, an argument), not by a bug."""


class FormatError(SonarSetError):
    """A store or file does not follow the SonarSet format."""


class GridMismatchError(SonarSetError):
    """Data or a model was made for another sensor grid."""


class InputValidationError(SonarSetError):
    """Several problems were found in an input; ``problems`` holds one line each."""

    def __init__(self, source: str, problems: list[str]):
        self.source = source
        self.problems = list(problems)
        head = f"{source}: {problems[0]}" if problems else source
        more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
        super().__init__(head + more)
