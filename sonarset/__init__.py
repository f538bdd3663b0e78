"""sonarset: in-air sonar prediction toolkit (SonarSet format, simulator, windows, metrics).

This package never imports torch; ``sonarset.models`` and ``sonarset.cli`` do, lazily.
"""

__version__ = "0.1.0"

from .errors import FormatError, GridMismatchError, InputValidationError, SonarSetError  # noqa: E402
from .schema import FORMAT_VERSION, Processing, RecordingMeta, RobotRig, RunAttrs, SensorGrid, StoreAttrs  # noqa: E402
from .store import Run, RunData, RunWriter, SonarStore, create_store, open_or_create_store, open_store  # noqa: E402

__all__ = [
    "__version__", "FORMAT_VERSION", "FormatError", "GridMismatchError", "InputValidationError",
    "Processing", "RecordingMeta", "RobotRig", "Run", "RunAttrs", "RunData", "RunWriter", "SensorGrid",
    "SonarSetError", "SonarStore", "StoreAttrs", "create_store", "open_or_create_store", "open_store",
]
