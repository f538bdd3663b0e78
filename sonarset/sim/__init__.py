"""The sonar simulator: worlds, a differential-drive robot, and an eRTIS-like imaging sonar.

The names below load on first use (PEP 562): the simulator compiles numba kernels, and the
command line reads ``sonarset.sim.spec`` for its help without paying for them.
"""

import importlib

_HOMES = {
    "generate": "generation",
    "ExplorationPolicy": "robot", "apply_slip": "robot", "integrate": "robot", "sensor_pose": "robot",
    "GenerationSpec": "spec",
    "plan_runs": "runs", "simulate_blocks": "runs",
    "SonarModel": "sonar", "visible_echoes": "sonar",
    "FAMILIES": "families", "corridor_world": "families", "lab_world": "families", "load_world": "families",
    "World": "world", "WorldSpec": "world",
}

__all__ = sorted(_HOMES)


def __getattr__(name: str):
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{home}"), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_HOMES))
