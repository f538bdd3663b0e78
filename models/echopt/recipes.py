"""Training recipes: a run's settings as a flat TOML file (the ``config`` of ``sonarset train``).

A recipe's keys are ``TrainConfig``'s fields (its ``command`` aside) plus ``store`` and ``out``, the
run's data and directory: the options of ``sonarset train`` with underscores, so a recipe and a
command line say the same things in the same words. Relative paths in a recipe are relative to the
directory ``sonarset train`` runs in, as on the command line. ``resume`` is no key: a recipe says
what to train, resuming is how to run it (continue the run in ``out``).

The card of a run records its resolved recipe (``training.recipe``) with paths relative to the run
directory, so a card names no directory of the machine it was trained on, and
``dump_recipe(card["training"]["recipe"])``, run from the run directory, trains the run again.

No torch here: the command line reads recipes before it loads the trainer.
"""

from __future__ import annotations

import dataclasses
import difflib
import os
import shlex
import typing

from sonarset.errors import SonarSetError
from sonarset.store.zarrio import is_url

from sonarset.models.echopt.train_config import TrainConfig

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

#: The settings a recipe may hold, in the order a dumped recipe lists them.
SETTINGS: dict[str, type] = {f.name: typing.get_type_hints(TrainConfig)[f.name]
                             for f in dataclasses.fields(TrainConfig) if f.name != "command"}
#: Every key a recipe may hold, with its type: where the run reads and writes, then its settings.
RECIPE_KEYS: dict[str, type] = {"store": str, "out": str, **SETTINGS}
#: Keys people will try that a recipe must not hold, and why.
NOT_KEYS = {
    "resume": "a recipe says what to train, not how to run it: resume it from the command line",
    "command": "the card records the command that ran; a recipe holds only settings",
}
#: ``init`` values that name a model rather than a path (models/echopt/checkpoint.py ``resolve``).
INIT_NAMES = ("", "pretrained")

_TYPE_NAMES = {str: "a string", int: "an integer", float: "a number", bool: "true or false"}


def load_recipe(path: str | os.PathLike) -> dict:
    """The settings of the recipe at ``path``, checked against ``RECIPE_KEYS`` (floats given as
    integers become floats); SonarSetError in one line naming the file, and the key, otherwise."""
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise SonarSetError(f"{path}: no such recipe file") from None
    except OSError as exc:
        raise SonarSetError(f"{path}: cannot read the recipe ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise SonarSetError(f"{path}: not a TOML recipe (not UTF-8 text)") from None
    except tomllib.TOMLDecodeError as exc:
        raise SonarSetError(f"{path}: not valid TOML: {' '.join(str(exc).split())}") from None
    return {key: _checked(path, key, value) for key, value in data.items()}


def _checked(path, key: str, value):
    if key in NOT_KEYS:
        raise SonarSetError(f"{path}: {key} is not a recipe key ({NOT_KEYS[key]})")
    if key not in RECIPE_KEYS:
        close = difflib.get_close_matches(key, RECIPE_KEYS, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else f" (keys: {', '.join(RECIPE_KEYS)})"
        raise SonarSetError(f"{path}: unknown key {key!r}{hint}")
    want = RECIPE_KEYS[key]
    # TOML's integers are not its floats, and a bool is no number here (Python's bool is an int)
    if want is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if type(value) is not want:
        raise SonarSetError(f"{path}: {key} must be {_TYPE_NAMES[want]}, got {_toml_value(value)} "
                            f"({_toml_type(value)})")
    return value


def _toml_type(value) -> str:
    kinds = {bool: "a boolean", int: "an integer", float: "a float", str: "a string", list: "an array",
             dict: "a table"}
    return kinds.get(type(value), f"a {type(value).__name__}")


def _toml_value(value) -> str:
    text = _scalar(value) if isinstance(value, (str, int, float)) else repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def config_of(recipe: dict, command: str | None = None) -> TrainConfig:
    """The TrainConfig of a recipe's settings (its ``store`` and ``out`` aside); what it omits keeps
    TrainConfig's default. ``command``: the command line that ran (default: this process's)."""
    settings = {k: v for k, v in recipe.items() if k in SETTINGS}
    return TrainConfig(**settings) if command is None else TrainConfig(**settings, command=command)


def recipe_of(cfg: TrainConfig, store: str | os.PathLike, out: str | os.PathLike,
              relative_to: str | os.PathLike | None = None) -> dict:
    """The full recipe of a run: every setting of ``cfg``, its store and run directory; with
    ``relative_to``, local paths (store, out, an ``init`` path) relative to that directory (a URL stays
    a URL)."""
    def where(path) -> str:
        return str(path) if relative_to is None else portable_path(path, relative_to)

    settings = {key: getattr(cfg, key) for key in SETTINGS}
    kind, init = cfg.init_parts()
    if init not in INIT_NAMES:
        settings["init"] = f"{kind}:{where(init)}" if kind else where(init)
    return {"store": where(store), "out": where(out), **settings}


def portable_path(path: str | os.PathLike, relative_to: str | os.PathLike) -> str:
    """``path`` relative to the directory ``relative_to`` (both as seen from this process's working
    directory); a URL as it is."""
    text = os.fspath(path)
    if is_url(text):
        return text
    try:
        return os.path.relpath(os.path.abspath(text.removeprefix("file://")), os.path.abspath(relative_to))
    except ValueError:  # another drive (Windows): no relative path exists
        return text


def portable_command(command: str, relative_to: str | os.PathLike) -> str:
    """A recorded command line (``shlex``-quoted) as ``sonarset ...``: the program's own path (an
    interpreter's, a virtual environment's) dropped, every absolute path argument (also in an
    option's ``=PATH``) relative to ``relative_to``."""
    try:
        argv = shlex.split(command)
    except ValueError:  # unbalanced quotes: not written by shlex.join
        argv = command.split()
    if not argv:
        return ""

    def portable(arg: str) -> str:
        flag, eq, value = arg.partition("=") if arg.startswith("--") else ("", "", arg)
        if os.path.isabs(value) or value.startswith("file:///"):
            value = portable_path(value, relative_to)
        return f"{flag}{eq}{value}"

    return shlex.join(["sonarset", *(portable(a) for a in argv[1:])])


def dump_recipe(recipe: dict, comment: str = "") -> str:
    """A recipe as TOML text that ``load_recipe`` reads back to the same dict: the keys in
    ``RECIPE_KEYS``'s order (others after them), after ``comment`` as ``#`` lines."""
    order = {key: i for i, key in enumerate(RECIPE_KEYS)}
    lines = [f"# {line}".rstrip() for line in comment.splitlines()]
    for key in sorted(recipe, key=lambda k: order.get(k, len(order))):
        lines.append(f"{_key(key)} = {_scalar(recipe[key])}")
    return "\n".join(lines) + "\n"


def _key(key: str) -> str:
    bare = key and all(c.isascii() and (c.isalnum() or c in "_-") for c in key)
    return key if bare else _string(key)


def _scalar(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if value != value:
            return "nan"
        if value in (float("inf"), float("-inf")):
            return "inf" if value > 0 else "-inf"
        return repr(value)  # always holds a '.' or an exponent: TOML reads it back as this float
    if isinstance(value, str):
        return _string(value)
    raise TypeError(f"a recipe holds strings, integers, floats and booleans, not {type(value).__name__}")


#: TOML basic strings escape the quote, the backslash and every control character but tab.
_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def _string(text: str) -> str:
    def escaped(c: str) -> str:
        if c in _ESCAPES:
            return _ESCAPES[c]
        if (ord(c) < 0x20 and c != "\t") or ord(c) == 0x7F:
            return f"\\u{ord(c):04X}"
        return c

    return '"' + "".join(escaped(c) for c in text) + '"'
