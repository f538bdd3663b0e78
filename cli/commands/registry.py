"""``sonarset models``: every predictor name this installation knows, and where it comes from."""

from __future__ import annotations

from rich.table import Table

from sonarset.cli.common import out, user_errors


@user_errors
def models() -> None:
    """List the predictors eval, view, demo and the experiments take by name: the built-ins, the
    shipped checkpoints, the checkpoint kinds (KIND:PATH) and installed plugins."""
    from sonarset.models.registry import PLUGIN_GROUP, available_predictors, shadowed_plugins

    table = Table()
    table.add_column("name", no_wrap=True)  # names and sources are what scripts grep for: one line each
    table.add_column("source", no_wrap=True)
    table.add_column("description", overflow="fold")
    for entry in available_predictors():
        table.add_row(entry.name, entry.source, entry.description)
    out.print(table)
    for note in shadowed_plugins().values():
        out.print(note, style="yellow", markup=False, highlight=False)
    out.print(f"Any other predictor: package.module:factory[:ARG] (ARG handed to the factory), or a plugin "
              f"(entry-point group {PLUGIN_GROUP!r}); see docs/guides/own-predictor.md.", markup=False, highlight=False)
