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
from sonarset.cli.common import err, labelled, out
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
    from sonarset.pool import Terminated, ending_on_signal, signal_exit_code, terminated_as_interrupt

    keep_freed_memory()
    said = False  # whether the command printed the line that says it was interrupted
    try:
        with terminated_as_interrupt():  # SIGTERM cleans up as Ctrl-C does (sonarset.pool)
            app()
    except KeyboardInterrupt as exc:  # one that arrived outside a command's own handler
        if signal_exit_code() is None:  # not from a signal (raised by code): said and done here
            err.print(labelled("error", "terminated" if isinstance(exc, Terminated) else "interrupted"))
            sys.exit(143 if isinstance(exc, Terminated) else 130)
    except SystemExit as exc:
        if signal_exit_code() is None:
            raise
        # A command's handler says it (and exits 130 or 143); typer turns an interrupt that no
        # handler caught into a silent exit 130, whose cause is the interrupt.
        said = exc.code in (130, 143) and not isinstance(getattr(exc.__context__, "__cause__", None),
                                                         KeyboardInterrupt)
    except Exception as exc:  # an unexpected error is a bug: say so in one line
        if signal_exit_code() is None:
            if os.environ.get("SONARSET_DEBUG"):
                raise
            err.print(labelled("internal error", f"{type(exc).__name__}: {exc} (set SONARSET_DEBUG=1 for details)"),
                      highlight=False, soft_wrap=True)
            sys.exit(70)
    if signal_exit_code() is None:
        return
    code = ending_on_signal(None if said else lambda what: err.print(labelled("error", what)))
    if "zarr" in sys.modules:  # its I/O loop, interrupted mid-request, would fill the exit with tracebacks
        from sonarset.store.zarrio import release_event_loop

        release_event_loop()
    sys.exit(code)


if __name__ == "__main__":
    main()
