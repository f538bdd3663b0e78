"""The sonar simulator: worlds, a differential-drive robot, and an eRTIS-like imaging sonar."""

from .generation import generate
from .robot import ExplorationPolicy, apply_slip, integrate, sensor_pose
from .runs import plan_runs, simulate_blocks
from .sonar import SonarModel, visible_echoes
from .families import FAMILIES, corridor_world, lab_world, load_world
from .world import World, WorldSpec

__all__ = ["FAMILIES", "ExplorationPolicy", "SonarModel", "World", "WorldSpec", "apply_slip", "corridor_world",
           "generate", "integrate", "lab_world", "load_world", "plan_runs", "sensor_pose",
           "simulate_blocks", "visible_echoes"]
