"""What every command shares: the consoles, one-line user errors, progress bars."""

from __future__ import annotations

import functools
from typing import Callable

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from sonarset.errors import InputValidationError, SonarSetError

out = Console(soft_wrap=True)
err = Console(stderr=True, soft_wrap=True)


def fail(message: str, code: int = 1) -> None:
    err.print(f"[bold red]error:[/] {message}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def user_errors(fn: Callable) -> Callable:
    """Turn library errors into one-line messages with exit code 1."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except InputValidationError as exc:
            for line in exc.problems:
                err.print(f"[bold red]error:[/] {exc.source}: {line}", highlight=False, soft_wrap=True)
            raise typer.Exit(1)
        except SonarSetError as exc:
            fail(str(exc))
        except KeyboardInterrupt:
            fail("interrupted", 130)
        except (OSError, MemoryError) as exc:
            fail(f"{getattr(exc, 'filename', None) or ''}{': ' if getattr(exc, 'filename', None) else ''}"
                 f"{exc.strerror if isinstance(exc, OSError) and exc.strerror else exc}")

    return wrapper


def progress_bar() -> Progress:
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TimeRemainingColumn(), console=err, transient=True, disable=not err.is_terminal)


def per_name_progress(bar: Progress) -> Callable[[str, int, int], None]:
    """A progress callback that keeps one bar per name (a run, a method)."""
    tasks: dict[str, int] = {}

    def progress(name: str, done: int, total: int) -> None:
        if name not in tasks:
            tasks[name] = bar.add_task(name, total=total)
        bar.update(tasks[name], completed=done)

    return progress
