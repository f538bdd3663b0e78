"""The commands of ``sonarset``, one module per area; cli/app.py registers them."""
