"""2D worlds: walls (line segments) and circles (poles, pillars, trees), spawn boxes, and fences.

The built-in worlds are families varied by seed (``families.py``: lab, corridor, orchard,
warehouse, rooms). Any world can also be loaded from a JSON or TOML file validated by
:class:`WorldSpec`. A fence is a segment the robot's motion treats as an obstacle and the sonar
does not see: the edge of an open scene (a field, a yard) that the exploration stays inside.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from sonarset.errors import SonarSetError


class WallSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    start: tuple[float, float]
    end: tuple[float, float]
    reflectivity: float = Field(1.0, ge=0, le=1)


class CircleSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    centre: tuple[float, float]
    radius: float = Field(gt=0, le=10)
    reflectivity: float = Field(1.0, ge=0, le=1)


class FenceSpec(BaseModel):
    """An invisible boundary segment: an obstacle to the robot's motion, no reflector."""

    model_config = ConfigDict(extra="forbid")
    start: tuple[float, float]
    end: tuple[float, float]


class SpawnBox(BaseModel):
    model_config = ConfigDict(extra="forbid")
    x: tuple[float, float]
    y: tuple[float, float]
    heading: tuple[float, float] = (-math.pi, math.pi)


class WorldSpec(BaseModel):
    """A world file (JSON or TOML). Lengths in metres, angles in radians."""

    model_config = ConfigDict(extra="forbid")
    name: str = "custom"
    walls: list[WallSpec] = Field(default_factory=list)
    circles: list[CircleSpec] = Field(default_factory=list)
    spawn: list[SpawnBox] = Field(min_length=1)
    fences: list[FenceSpec] = Field(default_factory=list)
    waypoint: tuple[float, float] | None = None


@dataclass
class World:
    """Geometry as flat arrays, ready for vectorised ray casting."""

    name: str
    seg_a: np.ndarray  # (S, 2) wall start points
    seg_b: np.ndarray  # (S, 2) wall end points
    seg_refl: np.ndarray  # (S,)
    circ_c: np.ndarray  # (C, 2) centres
    circ_r: np.ndarray  # (C,) radii
    circ_refl: np.ndarray  # (C,)
    spawn: list[SpawnBox] = field(default_factory=list)
    waypoint: tuple[float, float] | None = None
    fence_a: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (K, 2) fence start points
    fence_b: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    @classmethod
    def from_spec(cls, spec: WorldSpec) -> "World":
        w = spec.walls
        c = spec.circles
        return cls(
            spec.name,
            np.array([x.start for x in w], float).reshape(-1, 2), np.array([x.end for x in w], float).reshape(-1, 2),
            np.array([x.reflectivity for x in w], float), np.array([x.centre for x in c], float).reshape(-1, 2),
            np.array([x.radius for x in c], float), np.array([x.reflectivity for x in c], float),
            list(spec.spawn), spec.waypoint,
            np.array([f.start for f in spec.fences], float).reshape(-1, 2),
            np.array([f.end for f in spec.fences], float).reshape(-1, 2),
        )

    def to_spec(self) -> WorldSpec:
        return WorldSpec(
            name=self.name,
            walls=[WallSpec(start=tuple(a), end=tuple(b), reflectivity=r)
                   for a, b, r in zip(self.seg_a, self.seg_b, self.seg_refl)],
            circles=[CircleSpec(centre=tuple(c), radius=r, reflectivity=q)
                     for c, r, q in zip(self.circ_c, self.circ_r, self.circ_refl)],
            spawn=self.spawn, waypoint=self.waypoint,
            fences=[FenceSpec(start=tuple(a), end=tuple(b)) for a, b in zip(self.fence_a, self.fence_b)],
        )

    def obstacle_segments(self) -> tuple[np.ndarray, np.ndarray]:
        """(starts, ends) of every segment the robot cannot drive through: walls, then fences."""
        return (np.concatenate([self.seg_a.reshape(-1, 2), self.fence_a]),
                np.concatenate([self.seg_b.reshape(-1, 2), self.fence_b]))

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Distance from each point (N, 2) to the nearest wall, fence or circle surface."""
        points = np.atleast_2d(points)
        d = np.full(len(points), np.inf)
        seg_a, seg_b = self.obstacle_segments()
        if len(seg_a):
            ab = seg_b - seg_a
            ap = points[:, None, :] - seg_a[None]
            t = np.clip((ap * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0, 1)
            d = np.minimum(d, np.linalg.norm(ap - t[..., None] * ab, axis=-1).min(1))
        if len(self.circ_c):
            d = np.minimum(d, (np.linalg.norm(points[:, None] - self.circ_c[None], axis=-1) - self.circ_r).min(1))
        return d

    def sample_spawn(self, rng: np.random.Generator, clearance: float = 0.35, tries: int = 1000) -> np.ndarray:
        """A random collision-free pose (x, y, heading) in one of the spawn boxes."""
        for _ in range(tries):
            box = self.spawn[rng.integers(len(self.spawn))]
            pose = np.array([rng.uniform(*box.x), rng.uniform(*box.y), rng.uniform(*box.heading)])
            if self.clearance(pose[None, :2])[0] > clearance:
                return pose
        raise SonarSetError(f"world {self.name!r}: no collision-free spawn pose found in its spawn boxes")
