"""Importing recordings into a store, each validated completely before anything is written.

Two entry points: ``sonarset.ingest.images.import_recording`` (energyscapes a recording already
holds) and ``sonarset.ingest.raw.import_raw`` (microphone signals, beamformed by ``sonarset.sensor``).
Below them: ``metadata`` (the sidecars), ``files`` (the arrays on disk), ``target`` (where the run
is written, atomically).
"""
