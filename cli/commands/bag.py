"""``sonarset import-bag|export-bag``: ROS bags (ROS 1, ROS 2 sqlite3, MCAP) in, MCAP out."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from sonarset.cli.choices import Beamformer, ProcessingProfile, Stamps, value
from sonarset.cli.common import command_flags, err, labelled, out, per_name_progress, progress_bar, user_errors, with_flag
from sonarset.cli.options import MetaPath, OutStore, Overwrite, RunName, RunSplit

Topic = Optional[str]


@user_errors
def import_bag_(
    bag: Annotated[Path, typer.Argument(help="A ROS 2 bag directory (sqlite3 or MCAP), an .mcap file or a "
                                             "ROS 1 .bag.")],
    out_store: OutStore, meta: MetaPath = None, name: RunName = None, split: RunSplit = None,
    overwrite: Overwrite = False,
    images: Topic = typer.Option(None, "--images", help="Sonar image topic (ProjectedSonarImage or sensor_msgs/"
                                                        "Image); default: the only one."),
    raw: Topic = typer.Option(None, "--raw", help="Microphone signal topic (sonarset_msgs/MicrophoneArrayPing) to "
                                                  "beamform instead, with import-raw's sidecar."),
    cmd_vel: Topic = typer.Option(None, "--cmd-vel", help="Velocity command topic (Twist or TwistStamped); "
                                                          "default: the only one."),
    odom: Topic = typer.Option(None, "--odom", help="Odometry topic (nav_msgs/Odometry) for the poses; "
                                                    "default: the only one, if any."),
    stamps: Stamps = typer.Option("header", "--stamps", help="Message times: the headers' stamps, or when the "
                                                             "bag recorded each message."),
    cmd_offset: float = typer.Option(0.0, "--cmd-offset", help="Seconds added to every command time (a known "
                                                               "clock offset to the sensor)."),
    cmd_timeout: float = typer.Option(0.5, "--cmd-timeout", help="Seconds a command holds without a new one "
                                                                 "(the controller's cmd_vel timeout)."),
    processing: ProcessingProfile = typer.Option("ertis", "--processing", help="Energyscape profile (--raw)."),
    beamformer: Optional[Beamformer] = typer.Option(None, "--beamformer", help="Default: the profile's (--raw)."),
    workers: int = typer.Option(2, "--workers", min=1, help="Threads beamforming pings (--raw)."),
    allow_implausible: bool = typer.Option(False, "--allow-implausible",
                                           help="Import values the plausibility checks question (unit mistakes?); "
                                                "each is printed as a warning."),
) -> None:
    """Import a ROS bag's sonar images, velocity commands and odometry as runs: a few lost pings are recorded
    as gaps no window spans, a longer loss splits the run."""
    from sonarset.ingest.bag import import_bag

    def note(line: str) -> None:
        err.print(labelled("note", line, "cyan"), highlight=False, soft_wrap=True)

    def warn(line: str) -> None:  # a line may name the parameter that fixes it: said as the flag
        line = with_flag(line, "command_offset_s", command_flags(import_bag_), append=False)
        err.print(labelled("warning", line, "yellow"), highlight=False, soft_wrap=True)

    runs = import_bag(bag, out_store, images=images, raw=raw, commands=cmd_vel, odometry=odom, stamps=stamps.value,
                      command_offset_s=cmd_offset, command_timeout_s=cmd_timeout, meta_path=meta, name=name,
                      split=split, overwrite=overwrite, processing=processing.value, beamformer=value(beamformer),
                      workers=workers, allow_implausible=allow_implausible, note=note, warn=warn)
    frames = sum(r.n_frames for r in runs)
    names = ", ".join(r.name for r in runs) if len(runs) <= 4 else f"{runs[0].name} .. {runs[-1].name}"
    clock = runs[0].attrs.source.get("command_offset_estimate")
    unsure = "" if not clock or clock["confident"] else ", unsure"
    said = "" if not clock else (f"; commands vs images' motion: best at {clock['offset_s']:+.2f} s (R^2 "
                                 f"{clock['r2']:.2f}, {clock['sigma']:.0f} sigma{unsure})")
    out.print(f"imported {bag} -> {out_store}: {len(runs)} run(s) ({names}), "
              f"{frames} frames, split {runs[0].split}{said}", highlight=False)


@user_errors
def export_bag_(
    store: Annotated[str, typer.Argument(help="Store path or fsspec URL.")],
    out_file: Annotated[Path, typer.Argument(metavar="OUT", help="The MCAP file to write (*.mcap).")],
    run: Annotated[Optional[list[str]], typer.Option("--run", help="A run to export (repeat for several; "
                                                                   "default: every complete run).")] = None,
) -> None:
    """Export runs as MCAP (ProjectedSonarImage, TwistStamped, Odometry, tf) for ROS 2 tools, Foxglove and Rerun."""
    from sonarset.ingest.bag import export_bag

    with progress_bar() as bar:
        path = export_bag(store, out_file, runs=run, progress=per_name_progress(bar))
    out.print(f"wrote {path} ({path.stat().st_size / 2**20:.1f} MiB) and its sidecar {path.with_suffix('.json')}")
