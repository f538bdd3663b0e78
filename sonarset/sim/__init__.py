"""The sonar simulator: worlds, a differential-drive robot, and an eRTIS-like imaging sonar."""

from sonarset.sim.generation import generate
from sonarset.sim.robot import ExplorationPolicy, apply_slip, integrate, sensor_pose
from sonarset.sim.runs import GenerationSpec, plan_runs, simulate_blocks
from sonarset.sim.sonar import SonarModel, visible_echoes
from sonarset.sim.families import FAMILIES, corridor_world, lab_world, load_world
from sonarset.sim.world import World, WorldSpec

__all__ = ["FAMILIES", "ExplorationPolicy", "GenerationSpec", "SonarModel", "World", "WorldSpec", "apply_slip",
           "corridor_world", "generate", "integrate", "lab_world", "load_world", "plan_runs", "sensor_pose",
           "simulate_blocks", "visible_echoes"]
