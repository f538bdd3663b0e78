"""The ``sonarset`` command line: a thin layer over the library API. This module wires the commands
(cli/commands/) into one typer app, in the order ``--help`` lists them.

User errors (bad files, bad stores, bad arguments) end with one line on stderr and a non-zero
exit, never a traceback. Set SONARSET_DEBUG=1 to see the traceback of an unexpected error.
"""

from __future__ import annotations

import os
import sys

import typer

from sonarset import __version__

from sonarset.cli.commands import bag, ingest, model, registry, sim, store, view
from sonarset.cli.commands import benchmark
from sonarset.cli.common import err, out
from sonarset.cli.experiment import experiment_app

app = typer.Typer(
    name="sonarset",
    help="In-air sonar prediction: SonarSet stores, simulator, EchoPT and baselines.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.add_typer(experiment_app, name="experiment")


def _version(value: bool) -> None:
    if value:
        out.print(f"sonarset {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    pass


app.command()(store.info)
app.command()(store.validate)
app.command("import")(ingest.import_)
app.command("import-raw")(ingest.import_raw_)
app.command("import-bag")(bag.import_bag_)
app.command("export-bag")(bag.export_bag_)
app.command()(store.schema)
app.command()(sim.generate)
app.command()(store.show)
app.command("eval")(model.eval_)
app.command()(registry.models)
app.command()(model.train)
app.command()(model.demo)
app.command()(benchmark.benchmark)
app.command("export-onnx")(model.export_onnx_)
app.command()(view.view)


def main() -> None:
    from sonarset.perf import keep_freed_memory
    from sonarset.pool import Terminated, terminated_as_interrupt

    keep_freed_memory()
    try:
        with terminated_as_interrupt():  # SIGTERM cleans up as Ctrl-C does (sonarset.pool)
            app()
    except KeyboardInterrupt as exc:  # one that arrived outside a command's own handler
        err.print(f"[bold red]error:[/] {'terminated' if isinstance(exc, Terminated) else 'interrupted'}")
        sys.exit(143 if isinstance(exc, Terminated) else 130)
    except Exception as exc:  # an unexpected error is a bug: say so in one line
        if os.environ.get("SONARSET_DEBUG"):
            raise
        err.print(f"[bold red]internal error:[/] {type(exc).__name__}: {exc} (set SONARSET_DEBUG=1 for details)",
                  highlight=False, soft_wrap=True)
        sys.exit(70)


if __name__ == "__main__":
    main()
