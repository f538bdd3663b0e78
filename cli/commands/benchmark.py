"""``sonarset benchmark``: models on the frozen benchmark protocol, and results files compared."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from sonarset.cli.choices import Device, Precision
from sonarset.cli.common import out, progress_bar, user_errors
from sonarset.cli.options import ModelDevice, ModelPrecision


@user_errors
def benchmark(
    models: List[str] = typer.Argument(..., metavar="MODEL",
                                       help="Model specs as eval --models takes them (flow is always scored), or "
                                            "with --compare, results.json files."),
    out_dir: Path = typer.Option(Path("benchmark-out"), "--out", help="Directory for results.json and results.md."),
    quick: bool = typer.Option(False, "--quick", help="Protocol v1-quick: two families and the demo's lab, 1-minute "
                                                      "runs, 40 windows, horizons 1 and 3 (a smoke test; never "
                                                      "compares with v1)."),
    cache: Optional[Path] = typer.Option(None, "--cache", help="Folder of the protocol's stores (default: "
                                                               "$SONARSET_CACHE/benchmark/VERSION, else "
                                                               "~/.cache/sonarset/benchmark/VERSION)."),
    device: ModelDevice = Device("auto"),
    precision: ModelPrecision = Precision("auto"),
    compare: bool = typer.Option(False, "--compare", help="Print one table of the results files given (same "
                                                          "protocol version) instead of running."),
) -> None:
    """Score models on benchmark protocol v1: fresh test runs of every world family and the demo's
    lab run, against flow and the noise and observable ceilings, into one results file."""
    from sonarset.report.numbers import horizon_name
    from sonarset.models.benchmark import compare_results, run_benchmark
    from sonarset.models.benchmark.tables import summary_table

    if compare:
        out.print(compare_results(models), markup=False, highlight=False)
        return
    with progress_bar() as bar:
        tasks: dict[str, int] = {}

        def progress(name: str, done: int, total: int) -> None:
            if name not in tasks:
                tasks[name] = bar.add_task(name, total=total)
            bar.update(tasks[name], completed=done, total=total)

        def log(line: str) -> None:
            for name, task in list(tasks.items()):  # what is done leaves the screen with its line
                if bar.tasks[bar.task_ids.index(task)].finished:
                    bar.remove_task(task)
                    del tasks[name]
            bar.console.print(line, markup=False, highlight=False)

        results = run_benchmark(models, out_dir, quick, cache=cache, device=device.value, precision=precision.value,
                                progress=progress, log=log)
    longest = max(results["protocol"]["definition"]["horizons"])
    out.print(f"CC at {horizon_name(longest)}:\n{summary_table(results)}", markup=False, highlight=False)
    out.print(f"protocol {results['protocol']['version']}, {results['timings']['total']:.0f} s; results: "
              f"{out_dir / 'results.json'}, {out_dir / 'results.md'}", highlight=False)
