"""sonarset.cli: the ``sonarset`` command-line interface (a thin layer over the library)."""
