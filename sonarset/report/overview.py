"""What ``sonarset info`` and ``sonarset show`` tell about a store: its summary (the JSON
document), and the picture of one run's frame in the world it was driven through."""

from __future__ import annotations

import math
import os

from sonarset.errors import SonarSetError
from sonarset.store.store import SonarStore


def store_summary(store: SonarStore) -> dict:
    """Format version, grid, processing, rig, each complete run (split, frames, duration, image
    dtype, optional arrays), the incomplete runs, frames and bytes in all."""
    complete = store.runs()  # listing runs reads every run's attributes: once, not once per run
    runs = [store.run(n) for n in complete]
    rig = store.rig
    return {
        "store": store.location, "format_version": store.format_version, "grid": store.grid.model_dump(),
        "frame_rate_hz": store.attrs.frame_rate_hz, "created_by": store.attrs.created_by,
        "processing": store.processing.model_dump(mode="json"),
        "rig": rig.model_dump(mode="json") if rig is not None else None,
        "rig_recorded": store.attrs.rig is not None,
        "runs": [{"name": r.name, "split": r.split, "frames": r.n_frames,
                  "duration_s": float(r.read_time()[-1] - r.read_time()[0]),
                  "image_dtype": str(r.images.dtype),
                  "optional": [k for k in ("pose", "snr_db", "slip") if r.has(k)],
                  "world": _world_label(r.attrs.source)} for r in runs],
        "incomplete_runs": sorted(set(store.runs(include_incomplete=True)) - set(complete)),
        "frames": sum(r.n_frames for r in runs), "bytes": store.nbytes_stored(),
    }


def _world_label(source: dict | None) -> str | None:
    """``orchard #4521`` for a simulated run's world family and variant; None where none is recorded."""
    source = source or {}
    if "world" not in source:
        return None
    seed = source.get("world_seed")
    return f"{source['world']}" + (f" #{seed}" if seed is not None else "")


def describe_sensing(store: SonarStore) -> list[str]:
    """The grid (with its bin size), the processing and the robot rig, a line each."""
    g, rig = store.grid, store.rig
    provenance = " (from the simulator's run provenance)" if rig is not None and store.attrs.rig is None else ""
    return [f"grid: {g.describe()}, bins {g.range_step * 100:.3g} cm x {math.degrees(g.azimuth_step):.3g} deg",
            f"processing: {store.processing.describe()}",
            f"rig: {rig.describe() if rig is not None else 'not recorded'}{provenance}"]


def human_bytes(n: int | None) -> str:
    if n is None:
        return "n/a"
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{n} B"
        n /= 1024
    return str(n)


def simulated_world(source: dict):
    """The world a simulated run was driven through (its provenance names it), else None: a run
    from elsewhere, a world file that moved, or provenance that names no world."""
    if source.get("kind") != "simulator":
        return None
    from sonarset.sim.families import load_world

    try:
        return load_world(source["world"], int(source["world_seed"]))
    except (SonarSetError, KeyError, ValueError, TypeError):
        return None


def show(store: SonarStore, run: str | None, frame: int, out_png: str | os.PathLike) -> str:
    """Write a PNG of run ``run`` (default: the first complete run) at ``frame``: the world and the
    trajectory where known, and the energyscape as an image and as a polar fan."""
    from sonarset.report.plots import show_run

    name = run or (store.runs() or [None])[0]
    if name is None:
        raise SonarSetError(f"{store.location}: no complete runs")
    return show_run(store, name, frame, out_png, simulated_world(store.run(name).attrs.source))
