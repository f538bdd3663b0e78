"""The plausibility rules ``import`` applies (``sonarset.format.plausibility``), on a bag's runs.

Velocity commands, taken on the frames, against the rig (the existing store's, else the sidecar's;
without one, any ground robot's limits), the sensor grid the images give, and the frame interval
against physics (an echo's round trip, a sonar stream's slowest rate): values no in-air sonar on
a ground robot records, read as unit mistakes (a Twist in cm/s, ranges in millimetres). As for
``import``, each finding refuses the import unless ``allow_implausible`` lets it through as a
warning. (A frame interval against the store's declared rate is checked by ``importer`` itself.)
"""

from __future__ import annotations

import numpy as np

from sonarset.format import plausibility as plaus
from sonarset.format.attrs import RobotRig, SensorGrid

#: What a finding says after it, as ``import``'s do.
from sonarset.ingest.images import IMPLAUSIBLE_NOTE

__all__ = ["IMPLAUSIBLE_NOTE", "bag_implausible"]


def bag_implausible(runs: dict[str, dict[str, np.ndarray]], grid: SensorGrid | None, rig: RobotRig | None,
                    interval_s: float, commands_topic: str, frames_topic: str) -> list[str]:
    """The plausibility findings on a bag's runs (``importer._runs``'s arrays), one line each,
    naming the topic they come from."""
    found: list[str] = []
    if runs and rig is not None:  # beyond any robot (no rig) is no finding but an error: importer.load_bag
        velocity = np.concatenate([r["velocity"] for r in runs.values()])
        found += [f"topic {commands_topic!r}: {p.message}" for p in plaus.command_problems(velocity, rig)]
    if grid is not None:
        found += [f"topic {frames_topic!r}: {p.message}" for p in plaus.grid_problems(grid)]
        if interval_s > 0:
            found += [f"topic {frames_topic!r}: {p.message}"
                      for p in plaus.time_problems(np.array([0.0, interval_s]), None, grid.range_max_m)]
    return found
