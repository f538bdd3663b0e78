"""The experiments recorded for Rerun (the record option of `experiment control|slip`): the episodes.

Control: every episode under ``control/CONDITION/run_NNN`` on a ``step`` and a ``time`` timeline:
the robot's position (and its whole path, static), the SNR of each frame, whether a noise burst
was on, whether the detector flagged it and whether the frame was bridged by a prediction. Slip:
the paper trajectory under ``slip/``: the path, the slip factors over time, and each predictor's
slip signal per horizon and detector, beside the frame labels. Needs rerun-sdk (the ``view`` extra).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np


def entity_name(label: str) -> str:
    """A condition label as one entity path part: a checkpoint's path ('bursts+echopt:/runs/a/model')
    would otherwise open sub-entities at every '/'."""
    return re.sub(r"[^\w.-]+", "_", label).strip("_") or "_"


def record_control(res, out: str | os.PathLike) -> Path:
    """The control experiment's episodes (``ControlResult``) to the recording ``out``."""
    import rerun as rr
    import rerun.blueprint as rrb

    dt = res.rig.frame_interval_s
    rec = rr.RecordingStream("sonarset-control")
    rec.save(Path(out), default_blueprint=rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial2DView(origin="control", name="paths (x forward along the corridor, y left)"),
        rrb.TimeSeriesView(origin="control", name="SNR, bursts, bridged frames"))))
    for condition, episodes in res.episodes.items():
        for ep in episodes:
            base = f"control/{entity_name(condition)}/run_{int(ep['index']):03d}"
            pose = np.asarray(ep["pose"], float)
            rec.log(f"{base}/path", rr.LineStrips2D([pose[:, :2]]), static=True)
            rec.log(f"{base}/outcome", rr.TextDocument(f"{condition}: {ep['outcome']}"), static=True)
            series = {"snr_db": np.asarray(ep["snr_db"], float),
                      "burst": np.asarray(ep["burst"], float), "flagged": np.asarray(ep["flagged"], float),
                      "bridged": np.asarray(ep["predicted"], float)}
            for k in range(len(series["snr_db"])):
                rec.set_time("step", sequence=k)
                rec.set_time("time", duration=k * dt)
                rec.log(f"{base}/robot", rr.Points2D([pose[k, :2]], radii=0.1))
                for key, values in series.items():
                    rec.log(f"{base}/{key}", rr.Scalars(float(values[k])))
    rec.flush()
    rec.disconnect()
    return Path(out)


def record_slip(res, out: str | os.PathLike) -> Path:
    """The slip experiment's paper trajectory (``SlipResult.paper``) to the recording ``out``."""
    import rerun as rr
    import rerun.blueprint as rrb

    paper = res.paper
    dt = res.rig.frame_interval_s
    rec = rr.RecordingStream("sonarset-slip")
    rec.save(Path(out), default_blueprint=rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial2DView(origin="slip/map", name="trajectory"),
        rrb.Vertical(rrb.TimeSeriesView(origin="slip/factor", name="slip factors"),
                     rrb.TimeSeriesView(origin="slip/signal", name="slip signals")))))
    pose = np.asarray(paper["pose"], float)
    rec.log("slip/map/path", rr.LineStrips2D([pose[:, :2]]), static=True)
    slip = np.asarray(paper["slip"], float).reshape(len(pose), -1)
    for k in range(len(pose)):
        rec.set_time("frame", sequence=k)
        rec.set_time("time", duration=k * dt)
        rec.log("slip/map/robot", rr.Points2D([pose[k, :2]], radii=0.08))
        for j, side in enumerate(("left", "right")[:slip.shape[1]]):
            rec.log(f"slip/factor/{side}", rr.Scalars(float(slip[k, j])))
        for key, signal in paper["signals"].items():
            value = float(np.asarray(signal)[k])
            if np.isfinite(value):
                name, h, det = key.split("|")
                rec.log(f"slip/signal/{entity_name(name)}/H{h}/{det}", rr.Scalars(value))
    rec.flush()
    rec.disconnect()
    return Path(out)
