"""``sonarset generate``: simulated runs into a store."""

from __future__ import annotations

import math
from typing import Optional

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from dataclasses import fields

from sonarset.format.attrs import SensorGrid
from sonarset.sim.families import FAMILIES
from sonarset.sim.spec import DEFAULT_PROCESSING, DEFAULT_RUNS, GenerationSpec

from sonarset.cli.choices import ProcessingProfile, Psf
from sonarset.cli.common import err, out, user_errors


#: The grid a store gets unless --n-range or --n-azimuth say otherwise: the format's default.
GRID = SensorGrid.default()
#: The library's defaults of what a store holds (GenerationSpec): the options' defaults.
SPEC = {f.name: f.default for f in fields(GenerationSpec)}


@user_errors
def generate(
    out_store: str = typer.Argument(..., metavar="OUT", help="Store to write (created, or resumed)."),
    runs: Optional[int] = typer.Option(None, "--runs", min=0,
                                       help=f"Training runs of a single --world (default {DEFAULT_RUNS})."),
    minutes: float = typer.Option(SPEC["minutes"], "--minutes", min=0.0, help="Length of each run (5 Hz frames)."),
    test_runs: int = typer.Option(SPEC["test_runs"], "--test-runs", min=0,
                                  help="Test runs (split 'test') of each world, never for training."),
    workers: Optional[int] = typer.Option(None, "--workers", min=1, help="Parallel processes (default: all cores)."),
    seed: int = typer.Option(SPEC["seed"], "--seed", help="Master seed; same seed, same arrays, whatever the workers."),
    world: str = typer.Option(SPEC["world"], "--world",
                              help=f"A world family ({', '.join(FAMILIES)}; each run its own "
                                   "variant) or a JSON/TOML world file; or a mix with each world's training runs: "
                                   "lab:4,orchard:2,warehouse:2,rooms:2 (then no --runs)."),
    snr_db: float = typer.Option(SPEC["snr_db"], "--snr-db", help="SNR at the microphones, dB."),
    psf: Psf = typer.Option(SPEC["psf"], "--psf", help="Azimuth PSF: array (eRTIS delay-and-sum, with side lobes) or "
                                                  "mainlobe."),
    processing: ProcessingProfile = typer.Option(DEFAULT_PROCESSING, "--processing",
                                                 help="Images: ertis (DMAS3 + coherence factor, energyscape "
                                                      "post-processing, the sensor toolchain's) or raw (delay-and-sum "
                                                      "energy, format 1.0's)."),
    n_range: int = typer.Option(GRID.n_range, "--n-range", min=2,
                                help=f"Range bins over {GRID.range_min_m:g}-{GRID.range_max_m:g} m."),
    n_azimuth: int = typer.Option(GRID.n_azimuth, "--n-azimuth", min=2,
                                  help=f"Azimuth bins over {math.degrees(GRID.azimuth_min_rad):+g}.."
                                       f"{math.degrees(GRID.azimuth_max_rad):+g} deg."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler",
                                            help="Dask scheduler address (tcp://host:8786), or 'local' for a "
                                                 "LocalCluster of --workers processes; default: local processes."),
) -> None:
    """Simulate runs into a SonarSet store (a path or an fsspec URL); re-run the same command to resume."""
    import time

    from rich.progress import MofNCompleteColumn, TimeElapsedColumn

    from sonarset.sim import generate as gen
    from sonarset.sim.spec import world_mix

    grid = SensorGrid(**{**GRID.model_dump(), "n_range": n_range, "n_azimuth": n_azimuth})
    t0 = time.perf_counter()
    columns = [TextColumn("{task.description}", style="bold", markup=False), BarColumn(), MofNCompleteColumn(),
               TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), TimeRemainingColumn()]
    with Progress(*columns, console=err, disable=not err.is_terminal) as bar:
        tasks: dict[str, int] = {}
        started: dict[str, float] = {}

        def progress(name: str, done: int, total: int) -> None:
            if name not in tasks:
                tasks[name] = bar.add_task(name, total=total, rate="")
                started[name] = time.perf_counter()
            rate = done / max(time.perf_counter() - started[name], 1e-9)
            bar.update(tasks[name], completed=done, rate=f"{rate:,.0f} frames/s")

        written = gen(out_store, runs=runs, test_runs=test_runs, minutes=minutes, seed=seed, world=world,
                      snr_db=snr_db, psf=psf.value, processing=processing.value, workers=workers, grid=grid,
                      progress=progress, scheduler=scheduler)
    dt = time.perf_counter() - t0
    planned = sum(n + test_runs for _, n in world_mix(world, runs))
    out.print(f"{out_store}: wrote {len(written)} run(s) in {dt:.1f} s"
              + (f" ({planned - len(written)} already complete)" if len(written) < planned else ""))
