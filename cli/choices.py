"""The closed choices of the command line, as str Enums: typer checks a value against them and
lists them in ``--help``, so no command checks one by hand.

Where the library holds the list in a module that imports quickly (the schema), it is taken from
there; the others live in modules that import torch or the simulator, which ``--help`` must not
load, so they are written here and ``tests/test_cli.py`` checks them against the library's.
"""

from __future__ import annotations

import enum
from typing import Iterable, get_args

from sonarset.format.attrs import SCHEMAS, Processing


def _choices(name: str, values: Iterable[str]) -> type[enum.Enum]:
    """A str Enum whose members' values are ``values``, the strings users type."""
    return enum.Enum(name, {v: v for v in values}, type=str)


SchemaKind = _choices("SchemaKind", SCHEMAS)
Beamformer = _choices("Beamformer", get_args(Processing.model_fields["beamformer"].annotation))
ProcessingProfile = _choices("ProcessingProfile", ("ertis", "raw"))  # Processing.named
Psf = _choices("Psf", ("array", "mainlobe"))  # sim.sonar.BEAMS
Device = _choices("Device", ("auto", "cpu", "cuda"))  # models.checkpoint.resolve_device
Preset = _choices("Preset", ("small", "paper", "tiny"))  # models.echopt.PRESETS
Prior = _choices("Prior", ("none", "last", "flow"))  # models.echopt.PRIORS
Optimizer = _choices("Optimizer", ("adam", "adamw"))  # models.train
Schedule = _choices("Schedule", ("none", "cosine"))  # models.train
Precision = _choices("Precision", ("auto", "fp32", "bf16"))  # models.precision.PRECISIONS


def value(choice: enum.Enum | None) -> str | None:
    """The string a choice stands for (None stays None): what the library takes."""
    return None if choice is None else choice.value
