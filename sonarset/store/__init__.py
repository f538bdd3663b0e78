"""Zarr I/O of SonarSet stores: open, create, read and write them (spec/FORMAT.md)."""

from sonarset.store.remote import RemoteLimits
from sonarset.store.run import Run, RunData
from sonarset.store.store import SonarStore, create_store, open_or_create_store, open_store
from sonarset.store.writer import RunWriter

__all__ = ["RemoteLimits", "Run", "RunData", "RunWriter", "SonarStore", "create_store", "open_or_create_store", "open_store"]
