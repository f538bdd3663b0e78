"""``sonarset info|validate|schema|show``: reading and checking a store."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table
from rich.text import Text

from sonarset.cli.choices import SchemaKind
from sonarset.cli.common import err, labelled, out, progress_bar, user_errors


@user_errors
def info(
    store: str = typer.Argument(..., help="Store path or fsspec URL."),
    as_json: bool = typer.Option(False, "--json", help="Print machine-readable JSON."),
) -> None:
    """Summarise a store: format version, grid, runs, frames and size."""
    from sonarset.report.overview import describe_sensing, human_bytes, store_summary
    from sonarset.store.store import open_store

    s = open_store(store, check=True)
    summary = store_summary(s)
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    writer = s.attrs.created_by or "unknown writer"
    out.print(Text.assemble((str(s.location), "bold"), f"  SonarSet {s.format_version}  ({writer})"))
    for line in describe_sensing(s):
        out.print(line, highlight=False)
    table = Table("run", "split", "world", "frames", "duration", "images", "optional")
    for r in summary["runs"]:
        table.add_row(r["name"], r["split"], r["world"] or "-", str(r["frames"]), f"{r['duration_s']:.1f} s",
                      r["image_dtype"], ", ".join(r["optional"]) or "-")
    out.print(table)
    out.print(f"{len(summary['runs'])} complete run(s), {summary['frames']} frames, {human_bytes(summary['bytes'])} on disk")
    incomplete = summary["incomplete_runs"]
    if incomplete:
        out.print(f"{len(incomplete)} incomplete run(s) ignored: {', '.join(incomplete)}", style="yellow")


@user_errors
def validate(
    store: str = typer.Argument(..., help="Store path or fsspec URL."),
    quick: bool = typer.Option(False, "--quick", help="Check metadata only; do not read the data chunks."),
    consolidate: bool = typer.Option(False, "--consolidate",
                                     help="Rewrite stale consolidated metadata, then validate."),
    allow_implausible: bool = typer.Option(False, "--allow-implausible",
                                           help="Report implausible values (unit mistakes?) as warnings, not errors."),
) -> None:
    """Check a store against the SonarSet spec: exit 0 if valid, 1 with one line per problem."""
    from sonarset.store.validate import validate_store

    if consolidate:
        from sonarset.store.lock import writer_lock
        from sonarset.store.store import open_store

        with writer_lock(store):
            open_store(store, "r+").consolidate()
    with progress_bar() as bar:
        task = bar.add_task("validating", total=None)

        def progress(where: str, done: int, total: int) -> None:
            bar.update(task, description=where.rsplit("/", 2)[-2], completed=done, total=total)

        problems = validate_store(store, check_data=not quick, progress=progress)
    from sonarset.format.plausibility import Implausible

    allowed = [p for p in problems if allow_implausible and isinstance(p, Implausible)]
    problems = [p for p in problems if not (allow_implausible and isinstance(p, Implausible))]
    for p in allowed:
        err.print(labelled("warning", p, "yellow"), highlight=False, soft_wrap=True)
    if problems:
        for p in problems:
            label = "implausible" if isinstance(p, Implausible) else "invalid"
            err.print(labelled(label, p), highlight=False, soft_wrap=True)
        if any(isinstance(p, Implausible) for p in problems):
            err.print("note: if the implausible values are right, pass --allow-implausible", highlight=False)
        raise typer.Exit(1)
    out.print(f"{store}: valid SonarSet store" + (f" ({len(allowed)} implausible value(s) allowed)" if allowed else ""))


@user_errors
def schema(
    kind: SchemaKind = typer.Argument("store", help="The document."),
) -> None:
    """Print the JSON Schema of a SonarSet document: a store's or a run's attributes, or an import's metadata."""
    from sonarset.format.schemas import json_schema_text

    sys.stdout.write(json_schema_text(kind.value))


@user_errors
def show(
    store: str = typer.Argument(..., help="Store path or fsspec URL."),
    run: Optional[str] = typer.Option(None, "--run", help="Run name (default: the first)."),
    frame: int = typer.Option(0, "--frame", min=0, help="Frame index."),
    out_png: Path = typer.Option(Path("sonarset-show.png"), "--out", help="PNG to write."),
) -> None:
    """Plot the world and trajectory of a run and one energyscape (image and polar fan)."""
    from sonarset.report.overview import show as show_store
    from sonarset.store.store import open_store

    out.print(f"wrote {show_store(open_store(store, check=True), run, frame, out_png)}")
