"""``sonarset view``: a run and models' predictions of it as a Rerun recording."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path
from typing import Annotated, Optional

import typer

from sonarset.cli.choices import Device, Precision
from sonarset.cli.common import fail, out, per_name_progress, progress_bar, user_errors
from sonarset.cli.options import ModelDevice, ModelPrecision


def _frames(text: str | None) -> slice | None:
    """'A:B' (either end may be empty) as a slice."""
    if not text:
        return None
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        return slice(*(int(p) if p.strip() else None for p in parts))
    except ValueError:
        fail(f"--frames must be A:B (frame numbers, either may be empty), got {text!r}")


@user_errors
def view(
    store: Annotated[str, typer.Argument(help="Store path or fsspec URL.")],
    run: Annotated[Optional[str], typer.Option("--run", help="Run to record (default: the first complete run).")] = None,
    model: Annotated[Optional[list[str]], typer.Option(
        "--model", help="A predictor to show (repeat): any registered name (persistence, naive, flow, pretrained, "
                        "a plugin's; sonarset models lists them), KIND:PATH (echopt:PATH) or "
                        "package.module:factory[:ARG].")] = None,
    horizon: Annotated[int, typer.Option("--horizon", min=1, help="Auto-regressive steps of each prediction.")] = 1,
    frames: Annotated[Optional[str], typer.Option("--frames", help="Frames A:B (default: the whole run).")] = None,
    out_file: Annotated[Optional[Path], typer.Option(
        "--out", help="The .rrd file (default: RUN.rrd here, opened in the viewer when one can start).")] = None,
    device: ModelDevice = Device("cpu"),
    precision: ModelPrecision = Precision("auto"),
) -> None:
    """Record a run (sonar image and fan, map, commands) and models' predictions for the Rerun viewer."""
    from sonarset.models.view import record_run
    from sonarset.store.store import open_store

    s = open_store(store, check=True)
    target = out_file or Path(f"{run or (s.runs() or ['run'])[0]}.rrd")
    with progress_bar() as bar:
        path = record_run(s, run, target, models=model or [], horizon=horizon, frames=_frames(frames),
                          device=device.value, precision=precision.value, progress=per_name_progress(bar))
    out.print(f"wrote {path} ({path.stat().st_size / 2**20:.1f} MiB)")
    viewer = shutil.which("rerun")
    if out_file is None and viewer and (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        subprocess.Popen([viewer, str(path)], start_new_session=True, stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL)
        out.print("opened in the Rerun viewer")
    else:
        out.print(f"open it with: rerun {path}  (or drag it into https://app.rerun.io)")
