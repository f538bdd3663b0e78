"""Exceptions raised for bad input; the CLI turns them into one-line messages."""

from __future__ import annotations

import errno


class SonarSetError(Exception):
    """An error caused by the user's input (a file, a store, an argument), not by a bug.

    ``parameter`` names the argument the error is about, by its name in the library's API
    (``SonarSetError(f"minutes must be > 0, got {m}", parameter="minutes")``): the message speaks
    of values and parameters, and the command line shows the flag that sets that parameter
    (cli/common.py), so the library never needs to know its flags.
    """

    def __init__(self, *args: object, parameter: str | None = None):
        super().__init__(*args)
        self.parameter = parameter


class FormatError(SonarSetError):
    """A store or file does not follow the SonarSet format."""


class RemoteError(SonarSetError):
    """A remote store did not answer in time or kept failing (``sonarset.store.remote``): nothing
    is known about the store, so no check reports it as a problem of the store."""


class GridMismatchError(SonarSetError):
    """Data or a model was made for another sensor grid."""


class InputValidationError(SonarSetError):
    """Several problems were found in an input; ``problems`` holds one line each (the lines of
    ``sonarset.format.problems.Problem`` findings, or lines). ``parameter`` may be a tuple: the
    parameters some of the lines name."""

    def __init__(self, source: str, problems: list, *, parameter: str | tuple[str, ...] | None = None):
        self.source = source
        self.problems = [str(p) for p in problems]
        problems = self.problems
        head = f"{source}: {problems[0]}" if problems else source
        more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
        super().__init__(head + more, parameter=parameter)


def one_line(exc: BaseException) -> str:
    """An exception as one short line (its type and message), for an error that names a file."""
    text = " ".join(str(exc).split())
    if len(text) > 200:
        text = text[:197] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def first_os_error(exc: OSError) -> OSError:
    """The first of a chain of OSErrors: a writer's clean-up can fail on the same disk (or race the
    writes still in flight) and raise its own error, but the first failure is the one to report."""
    while isinstance(exc.__context__, OSError):
        exc = exc.__context__
    return exc


def os_error_reason(exc: OSError) -> str:
    """Why a write failed, in words ("no space left on device" for a full disk)."""
    if exc.errno == errno.ENOSPC:
        return "no space left on device"
    return exc.strerror or str(exc) or type(exc).__name__
