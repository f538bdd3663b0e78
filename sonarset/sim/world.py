"""2D worlds: walls (line segments) and circles (poles, pillars, trees), plus spawn boxes.

Built-in worlds: ``lab`` (an office floor with rooms, a corridor, pillars, a row of poles and
clutter, varied by seed) for data collection, and ``corridor`` (two rows of circular reflectors
with spawn boxes and a waypoint) for the control experiment. Any world can also be loaded from a
JSON or TOML file validated by :class:`WorldSpec`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..errors import SonarSetError
from ..schema import pydantic_problems


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
        )

    def to_spec(self) -> WorldSpec:
        return WorldSpec(
            name=self.name,
            walls=[WallSpec(start=tuple(a), end=tuple(b), reflectivity=r) for a, b, r in zip(self.seg_a, self.seg_b, self.seg_refl)],
            circles=[CircleSpec(centre=tuple(c), radius=r, reflectivity=q) for c, r, q in zip(self.circ_c, self.circ_r, self.circ_refl)],
            spawn=self.spawn, waypoint=self.waypoint,
        )

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Distance from each point (N, 2) to the nearest wall or circle surface."""
        points = np.atleast_2d(points)
        d = np.full(len(points), np.inf)
        if len(self.seg_a):
            ab = self.seg_b - self.seg_a
            ap = points[:, None, :] - self.seg_a[None]
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


def _box(x0, y0, x1, y1, refl=1.0) -> list[WallSpec]:
    p = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    return [WallSpec(start=p[i], end=p[(i + 1) % 4], reflectivity=refl) for i in range(4)]


def lab_world(seed: int = 0) -> World:
    """An office/lab floor, 14 x 10 m: three rooms with doors, a corridor, pillars, a row of poles,
    and clutter (boxes, table legs). Positions and sizes vary with ``seed``; the topology does not,
    so every seed has walls, corridors and rows of poles like the experiments' scenes."""
    rng = np.random.default_rng(seed)
    W, H = 14.0, 10.0
    walls = _box(0, 0, W, H)
    circles: list[CircleSpec] = []
    # Corridor along y in [cy, cy + cw], walls with door gaps into the rooms above.
    cy = rng.uniform(3.2, 3.8)
    cw = rng.uniform(1.6, 2.2)
    y2 = cy + cw
    xs = np.sort(rng.uniform([4.0, 8.5], [5.5, 10.0]))  # room dividers above the corridor
    doors = [rng.uniform(x + 0.6, x + 2.4) for x in (0.0, xs[0], xs[1])]
    gap = 0.9
    xcuts = [0.0] + [d for d in doors] + [W]
    for i, d in enumerate(doors):
        lo = xcuts[i] if i == 0 else doors[i - 1] + gap / 2
        walls.append(WallSpec(start=(lo, y2), end=(d - gap / 2, y2)))
    walls.append(WallSpec(start=(doors[-1] + gap / 2, y2), end=(W, y2)))
    for x in xs:
        walls.append(WallSpec(start=(x, y2), end=(x, H)))
    # Lower corridor wall: open at both ends into the lower hall, with one wide opening.
    open_x = rng.uniform(5.0, 9.0)
    walls.append(WallSpec(start=(2.0, cy), end=(open_x - 0.8, cy), reflectivity=0.9))
    walls.append(WallSpec(start=(open_x + 0.8, cy), end=(W - 2.0, cy), reflectivity=0.9))
    # Lower hall: pillars and a row of thin poles (like the control experiment's corridor).
    for x in rng.uniform(1.5, W - 1.5, 2):
        circles.append(CircleSpec(centre=(x, rng.uniform(1.2, cy - 1.0)), radius=rng.uniform(0.15, 0.3)))
    px = rng.uniform(2.0, 4.0)
    py = rng.uniform(0.9, 1.4)
    for k in range(int(rng.integers(6, 11))):
        circles.append(CircleSpec(centre=(px + 0.45 * k, py), radius=0.04, reflectivity=0.8))
    # Rooms: clutter boxes and table legs.
    rooms = [(0.0, xs[0]), (xs[0], xs[1]), (xs[1], W)]
    for x0, x1 in rooms:
        bx, by = rng.uniform(x0 + 0.6, x1 - 1.4), rng.uniform(y2 + 1.4, H - 1.2)
        walls += _box(bx, by, bx + rng.uniform(0.4, 0.9), by + rng.uniform(0.3, 0.6), refl=0.7)
        tx, ty = rng.uniform(x0 + 0.8, x1 - 1.6), rng.uniform(y2 + 1.2, H - 1.4)
        for dx, dy in ((0, 0), (1.0, 0), (0, 0.6), (1.0, 0.6)):
            circles.append(CircleSpec(centre=(tx + dx, ty + dy), radius=0.025, reflectivity=0.6))
    spawn = [SpawnBox(x=(1.0, W - 1.0), y=(cy + 0.5, y2 - 0.5)), SpawnBox(x=(1.0, W - 1.0), y=(0.6, cy - 0.6))]
    world = World.from_spec(WorldSpec(name=f"lab-{seed}", walls=walls, circles=circles, spawn=spawn))
    return world


def corridor_world(length: float = 12.0, half_width: float = 0.8, spacing: float = 0.4, radius: float = 0.05) -> World:
    """The control experiment's corridor: two rows of poles, a spawn box at one end, a waypoint at the other."""
    xs = np.arange(0.0, length + 1e-9, spacing)
    circles = [CircleSpec(centre=(float(x), s * half_width), radius=radius) for x in xs for s in (-1, 1)]
    spawn = [SpawnBox(x=(0.4, 1.2), y=(-0.25, 0.25), heading=(-0.35, 0.35))]
    return World.from_spec(WorldSpec(name="corridor", circles=circles, spawn=spawn, waypoint=(length - 0.5, 0.0)))


BUILTIN = {"lab": lab_world, "corridor": lambda seed=0: corridor_world()}


def load_world(name_or_path: str, seed: int = 0) -> World:
    """A built-in world by name (``lab``, ``corridor``) or a JSON/TOML world file."""
    if name_or_path in BUILTIN:
        return BUILTIN[name_or_path](seed)
    path = Path(name_or_path)
    if not path.is_file():
        raise SonarSetError(f"{name_or_path}: not a built-in world ({', '.join(BUILTIN)}) nor a world file")
    try:
        text = path.read_text()
        if path.suffix == ".toml":
            import tomllib

            doc = tomllib.loads(text)
        else:
            doc = json.loads(text)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise SonarSetError(f"{path}: cannot parse world file ({exc})") from None
    try:
        return World.from_spec(WorldSpec.model_validate(doc))
    except ValidationError as exc:
        raise SonarSetError(f"{path}: {pydantic_problems(exc)[0]}") from None
