"""The closed choices of the command line, as str Enums: typer checks a value against them and
lists them in ``--help``, so no command checks one by hand.

Each is made from the library's own list, in a module that imports neither torch nor the simulator
(which ``--help`` must not load).
"""

from __future__ import annotations

import enum
from typing import Iterable

from sonarset.format.attrs import BEAMFORMERS, PROCESSING_PROFILES
from sonarset.format.schemas import SCHEMAS
from sonarset.sensor.ertis import AZIMUTH_PSFS

from sonarset.models.echopt.config import INPUTS, PRIORS
from sonarset.models.echopt.precision import DEVICES, PRECISIONS
from sonarset.models.echopt.train_config import MODEL_KINDS, OPTIMIZERS, SCHEDULES, STEP_WEIGHTS, TRAINABLE
from sonarset.ingest.bag.reader import STAMPS


def _choices(name: str, values: Iterable[str]) -> type[enum.Enum]:
    """A str Enum whose members' values are ``values``, the strings users type."""
    return enum.Enum(name, {v: v for v in values}, type=str)


SchemaKind = _choices("SchemaKind", SCHEMAS)
Beamformer = _choices("Beamformer", BEAMFORMERS)
ProcessingProfile = _choices("ProcessingProfile", PROCESSING_PROFILES)
Psf = _choices("Psf", AZIMUTH_PSFS)
Device = _choices("Device", DEVICES)
Prior = _choices("Prior", PRIORS)
Inputs = _choices("Inputs", INPUTS)
Optimizer = _choices("Optimizer", OPTIMIZERS)
Schedule = _choices("Schedule", SCHEDULES)
StepWeights = _choices("StepWeights", STEP_WEIGHTS)
Trainable = _choices("Trainable", TRAINABLE)
Precision = _choices("Precision", PRECISIONS)
ModelKind = _choices("ModelKind", MODEL_KINDS)
Stamps = _choices("Stamps", STAMPS)


def value(choice: enum.Enum | None) -> str | None:
    """The string a choice stands for (None stays None): what the library takes."""
    return None if choice is None else choice.value
