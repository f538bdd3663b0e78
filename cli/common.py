"""What every command shares: the consoles, one-line user errors, progress bars."""

from __future__ import annotations

import functools
import inspect
import re
import typing
from typing import Callable

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
from rich.text import Text
from typer.models import OptionInfo

from sonarset.errors import InputValidationError, SonarSetError
from sonarset.pool import Terminated

# Neither reads markup or emoji codes in what it prints: names, paths and messages come from users
# and their files ("[/]" in a predictor's error was a traceback, ":factory:" an emoji); styles are
# given as Text (``labelled``).
out = Console(soft_wrap=True, markup=False, emoji=False)
err = Console(stderr=True, soft_wrap=True, markup=False, emoji=False)


def labelled(label: str, text: str, style: str = "bold red") -> Text:
    """``label:`` in ``style``, then ``text`` as it is."""
    return Text.assemble((f"{label}:", style), " ", str(text))


def fail(message: str, code: int = 1) -> None:
    err.print(labelled("error", message), highlight=False, soft_wrap=True)
    raise typer.Exit(code)


#: Library parameter names that a command's option spells differently (the option's Python name).
PARAMETER_OPTIONS = {"meta_path": "meta", "max_time_s": "max_time", "model_specs": "models", "commands": "cmd_vel",
                     "odometry": "odom", "command_offset_s": "cmd_offset", "command_timeout_s": "cmd_timeout",
                     "runs": "run", "run_name": "run"}


def _option_infos(hint) -> list[OptionInfo]:
    """The typer options declared in an annotation (``Annotated[..., typer.Option(...)]``, also
    inside an ``Optional``)."""
    found = [m for m in getattr(hint, "__metadata__", ()) if isinstance(m, OptionInfo)]
    return found + [i for arg in typing.get_args(hint) for i in _option_infos(arg)]


def command_flags(fn: Callable) -> dict[str, str]:
    """{parameter name: long flag} of a command function, read from its own option declarations
    (a trailing underscore dropped: ``compile_`` is ``compile``)."""
    hints = typing.get_type_hints(fn, include_extras=True)
    flags = {}
    for name, param in inspect.signature(fn).parameters.items():
        for info in [param.default, *_option_infos(hints.get(name))]:
            if isinstance(info, OptionInfo):
                decls = [d.split("/")[0] for d in info.param_decls or () if d.startswith("--")]
                flags[name.rstrip("_")] = decls[0] if decls else "--" + name.rstrip("_").replace("_", "-")
    return flags


def with_flag(message: str, parameter: str | None, flags: dict[str, str], append: bool = True) -> str:
    """A library message as the command line says it, with the flag (of ``flags``) that sets the
    library's ``parameter``: in place of the parameter's name where the message, or a parenthesis
    in it, opens with that name ("batch_size 3 is ..." -> "--batch-size 3 is ...", "(allow_implausible
    imports it)" -> "(--allow-implausible imports it)"), else (``append``) after the message in parentheses. A
    parameter no option sets (the command chose its value) leaves the message as it is."""
    flag = flags.get(PARAMETER_OPTIONS.get(parameter, parameter)) if parameter else None
    if flag is None:
        return message
    named = re.compile(rf"(^|\(){re.escape(parameter)}(?![\w-])")
    if named.search(message):
        return named.sub(lambda m: m[1] + flag, message)
    return f"{message} ({flag})" if append else message


def user_errors(fn: Callable) -> Callable:
    """Turn library errors into one-line messages with exit code 1."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except InputValidationError as exc:
            flags = command_flags(fn)
            named = exc.parameter if isinstance(exc.parameter, tuple) else (exc.parameter,)
            for line in exc.problems:
                # a parameter is about some of the lines (those that name it), not every one
                for parameter in named:
                    line = with_flag(line, parameter, flags, append=False)
                err.print(labelled("error", f"{exc.source}: {line}"), highlight=False, soft_wrap=True)
            raise typer.Exit(1) from None
        except SonarSetError as exc:
            fail(with_flag(str(exc), exc.parameter, command_flags(fn)))
        except Terminated:
            fail("terminated", 143)
        except KeyboardInterrupt:
            fail("interrupted", 130)
        except (OSError, MemoryError) as exc:
            fail(f"{getattr(exc, 'filename', None) or ''}{': ' if getattr(exc, 'filename', None) else ''}"
                 f"{exc.strerror if isinstance(exc, OSError) and exc.strerror else exc}")

    return wrapper


def progress_bar() -> Progress:
    return Progress(TextColumn("{task.description}", style="bold", markup=False), BarColumn(),
                    TextColumn("{task.completed}/{task.total}"), TimeRemainingColumn(), console=err, transient=True,
                    disable=not err.is_terminal)


def per_name_progress(bar: Progress) -> Callable[[str, int, int], None]:
    """A progress callback that keeps one bar per name (a run, a method)."""
    tasks: dict[str, int] = {}

    def progress(name: str, done: int, total: int) -> None:
        if name not in tasks:
            tasks[name] = bar.add_task(name, total=total)
        bar.update(tasks[name], completed=done)

    return progress
