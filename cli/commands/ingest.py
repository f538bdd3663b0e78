"""``sonarset import|import-raw``: external recordings into a store, validated completely first."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from sonarset.cli.choices import Beamformer, ProcessingProfile, value
from sonarset.cli.common import err, labelled, out, progress_bar, user_errors
from sonarset.cli.options import MetaPath, OutStore, Overwrite, RunName, RunSplit


@user_errors
def import_(
    src: Annotated[Path, typer.Argument(help="A .npz file, or a directory of .npy files with recording.json.")],
    out_store: OutStore, meta: MetaPath = None, name: RunName = None, split: RunSplit = None, overwrite: Overwrite = False,
    allow_implausible: bool = typer.Option(False, "--allow-implausible",
                                           help="Import values the plausibility checks question (unit mistakes?); "
                                                "each is printed as a warning."),
) -> None:
    """Validate an external recording completely, then write it as one run of a store."""
    from sonarset.ingest.images import import_recording

    def warn(line: str) -> None:
        err.print(labelled("warning", line, "yellow"), highlight=False, soft_wrap=True)

    run = import_recording(src, out_store, meta_path=meta, name=name, split=split, overwrite=overwrite,
                           allow_implausible=allow_implausible, warn=warn)
    out.print(f"imported {src} -> {out_store}/{run.name} ({run.n_frames} frames, split {run.split})")


@user_errors
def import_raw_(
    src: Annotated[Path, typer.Argument(help="Microphone signals: a .npz, or a directory of .npy files with "
                                             "recording.json.")],
    out_store: OutStore, meta: MetaPath = None, name: RunName = None, split: RunSplit = None, overwrite: Overwrite = False,
    processing: ProcessingProfile = typer.Option("ertis", "--processing", help="Energyscape profile."),
    beamformer: Optional[Beamformer] = typer.Option(None, "--beamformer", help="Default: the profile's."),
    workers: int = typer.Option(2, "--workers", min=1, help="Threads beamforming measurements."),
) -> None:
    """Beamform raw microphone recordings into energyscapes, validated completely, as one run of a store."""
    from sonarset.ingest.raw import import_raw

    with progress_bar() as bar:
        task = bar.add_task("beamforming", total=None)
        run = import_raw(src, out_store, meta_path=meta, name=name, split=split, processing=processing.value,
                         beamformer=value(beamformer), overwrite=overwrite, workers=workers,
                         progress=lambda done, total: bar.update(task, completed=done, total=total))
    out.print(f"imported {src} -> {out_store}/{run.name} ({run.n_frames} frames, split {run.split}, "
              f"{run.store.processing.describe()})", highlight=False)
