"""sonarset: in-air sonar prediction toolkit (SonarSet format, simulator, windows, metrics).

This package never imports torch; ``sonarset.models`` and ``sonarset.cli`` do, lazily.
"""

from sonarset.version import __version__
from sonarset.errors import FormatError, GridMismatchError, InputValidationError, RemoteError, SonarSetError
from sonarset.format.attrs import FORMAT_VERSION, Processing, RobotRig, RunAttrs, SensorGrid, StoreAttrs
from sonarset.format.sidecars import RecordingMeta
from sonarset.store import RemoteLimits, Run, RunData, RunWriter, SonarStore, create_store, open_or_create_store, open_store

__all__ = [
    "__version__", "FORMAT_VERSION", "FormatError", "GridMismatchError", "InputValidationError",
    "Processing", "RecordingMeta", "RemoteError", "RemoteLimits", "RobotRig", "Run", "RunAttrs", "RunData", "RunWriter",
    "SensorGrid",
    "SonarSetError", "SonarStore", "StoreAttrs", "create_store", "open_or_create_store", "open_store",
]
