"""Built-in world families: procedural 2D worlds, one variant per seed.

Each family keeps its kind of scene and varies its geometry with the seed (lengths, spacings,
sizes, reflectivities, gaps), with spawn boxes that the exploration policy can drive out of:

- ``lab``: an office floor, 14 x 10 m: rooms with doors, a corridor, pillars, a row of poles, clutter.
- ``corridor``: two rows of poles. Seed 0 is the control experiment's corridor (12 m, poles
  0.8 m either side of the centre line every 0.4 m); other seeds vary its length, width, pole
  spacing, radii and reflectivity, drop some poles, and sometimes put walls behind the rows.
- ``orchard``: rows of trees (trunk radii, spacing and row spacing vary) with jitter, gaps and posts.
- ``warehouse``: an outer hall with rack aisles (racks with uprights), a pillar grid and pallets.
- ``rooms``: a floor of rooms with angled walls (cut corners, slanted partitions) and doors,
  furniture and table legs.

Scenes without an enclosing wall (corridor, orchard) are bounded by a fence: segments the robot
never drives through and the sonar does not see (a field's edge), so that a run explores the
scene instead of wandering into empty space.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Callable

import numpy as np
from pydantic import ValidationError

from sonarset.errors import SonarSetError
from sonarset.format.problems import pydantic_problems
from sonarset.sim.world import CircleSpec, FenceSpec, SpawnBox, WallSpec, World, WorldSpec


def _box(x0, y0, x1, y1, refl=1.0) -> list[WallSpec]:
    p = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    return [WallSpec(start=p[i], end=p[(i + 1) % 4], reflectivity=refl) for i in range(4)]


def _rotated_box(cx, cy, w, h, angle, refl=1.0) -> list[WallSpec]:
    """A w x h box centred at (cx, cy), turned by ``angle`` (rad)."""
    c, s = math.cos(angle), math.sin(angle)
    corners = [(cx + c * x - s * y, cy + s * x + c * y) for x, y in ((-w / 2, -h / 2), (w / 2, -h / 2),
                                                                    (w / 2, h / 2), (-w / 2, h / 2))]
    return [WallSpec(start=corners[i], end=corners[(i + 1) % 4], reflectivity=refl) for i in range(4)]


def _fence(x0, y0, x1, y1) -> list[FenceSpec]:
    p = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    return [FenceSpec(start=p[i], end=p[(i + 1) % 4]) for i in range(4)]


def _clear_of(spec_walls: list[WallSpec], circles: list[CircleSpec], point, margin: float) -> bool:
    """Is ``point`` at least ``margin`` away from every wall and circle placed so far?"""
    world = World.from_spec(WorldSpec(walls=spec_walls, circles=circles, spawn=[SpawnBox(x=(0, 1), y=(0, 1))]))
    return bool(world.clearance(np.asarray(point, float)[None])[0] >= margin)


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
    return World.from_spec(WorldSpec(name=f"lab-{seed}", walls=walls, circles=circles, spawn=spawn))


def corridor_world(length: float = 12.0, half_width: float = 0.8, spacing: float = 0.4, radius: float = 0.05) -> World:
    """The control experiment's corridor: two rows of poles, a spawn box at one end, a waypoint at the other."""
    xs = np.arange(0.0, length + 1e-9, spacing)
    circles = [CircleSpec(centre=(float(x), s * half_width), radius=radius) for x in xs for s in (-1, 1)]
    spawn = [SpawnBox(x=(0.4, 1.2), y=(-0.25, 0.25), heading=(-0.35, 0.35))]
    return World.from_spec(WorldSpec(name="corridor", circles=circles, spawn=spawn, waypoint=(length - 0.5, 0.0)))


def corridor_family(seed: int = 0) -> World:
    """Corridors of poles varied by seed; seed 0 is the control experiment's (``corridor_world()``)."""
    if seed == 0:
        return corridor_world()
    rng = np.random.default_rng(seed)
    length = rng.uniform(8.0, 16.0)
    half = rng.uniform(0.6, 1.2)
    spacing = rng.uniform(0.3, 0.8)
    radius = rng.uniform(0.03, 0.12)
    refl = rng.uniform(0.6, 1.0)
    drop = rng.uniform(0.0, 0.15)
    circles = []
    for s in (-1, 1):
        for x in np.arange(0.0, length + 1e-9, spacing):
            if rng.random() < drop:
                continue
            jx, jy = rng.normal(0, 0.03 * spacing, 2)
            circles.append(CircleSpec(centre=(float(x + jx), float(s * half + jy)),
                                      radius=float(radius * rng.uniform(0.85, 1.15)), reflectivity=float(refl)))
    walls: list[WallSpec] = []
    if rng.random() < 0.5:  # a corridor inside a building: walls behind the rows of poles
        off = half + rng.uniform(0.4, 1.2)
        wr = float(rng.uniform(0.7, 1.0))
        walls += [WallSpec(start=(-1.0, s * off), end=(length + 1.0, s * off), reflectivity=wr) for s in (-1, 1)]
    reach = half + 1.6
    spawn = [SpawnBox(x=(0.4, 1.2), y=(-0.25, 0.25), heading=(-0.35, 0.35)),
             SpawnBox(x=(0.5, length - 0.5), y=(-half + 0.35, half - 0.35))]
    return World.from_spec(WorldSpec(name=f"corridor-{seed}", walls=walls, circles=circles, spawn=spawn,
                                     fences=_fence(-1.5, -reach, length + 1.5, reach),
                                     waypoint=(length - 0.5, 0.0)))


def orchard_world(seed: int = 0) -> World:
    """Rows of trees along x with jittered positions, gaps (missing trees) and row-end posts."""
    rng = np.random.default_rng(seed)
    n_rows = int(rng.integers(3, 7))
    row_gap = rng.uniform(2.2, 4.0)
    tree_gap = rng.uniform(1.0, 2.5)
    length = rng.uniform(10.0, 18.0)
    trunk = rng.uniform(0.05, 0.2)
    jitter = rng.uniform(0.0, 0.3)
    missing = rng.uniform(0.05, 0.25)
    refl = rng.uniform(0.5, 0.9)
    circles = []
    for i in range(n_rows):
        y = i * row_gap
        for x in np.arange(0.0, length + 1e-9, tree_gap):
            if rng.random() < missing:
                continue
            circles.append(CircleSpec(centre=(float(x + rng.uniform(-jitter, jitter)),
                                              float(y + rng.uniform(-jitter, jitter) / 2)),
                                      radius=float(trunk * rng.uniform(0.6, 1.4)),
                                      reflectivity=float(refl * rng.uniform(0.8, 1.0))))
        for x in (-0.8, length + 0.8):  # trellis posts at the row ends
            circles.append(CircleSpec(centre=(x, y), radius=0.04, reflectivity=0.9))
    width = (n_rows - 1) * row_gap
    spawn = [SpawnBox(x=(0.5, length - 0.5), y=(i * row_gap + 0.6, (i + 1) * row_gap - 0.6)) for i in range(n_rows - 1)]
    spawn.append(SpawnBox(x=(-2.5, -1.5), y=(0.0, width)))  # the headland at the row ends
    return World.from_spec(WorldSpec(name=f"orchard-{seed}", circles=circles, spawn=spawn,
                                     fences=_fence(-3.5, -2.0, length + 3.5, width + 2.0)))


def warehouse_world(seed: int = 0) -> World:
    """A hall with parallel rack rows (aisles between them, cross aisles at their ends), rack
    uprights, a grid of pillars in the open bay, and pallets on the floor."""
    rng = np.random.default_rng(seed)
    W, H = rng.uniform(16.0, 24.0), rng.uniform(12.0, 18.0)
    walls = _box(0, 0, W, H, refl=float(rng.uniform(0.8, 1.0)))
    circles: list[CircleSpec] = []
    depth, aisle = rng.uniform(0.9, 1.3), rng.uniform(1.8, 3.0)
    x0, x1 = rng.uniform(2.0, 3.0), W - rng.uniform(2.0, 3.0)
    bay = rng.uniform(3.5, 5.5)  # open bay along the bottom wall: pillars and pallets
    rack_refl = float(rng.uniform(0.6, 1.0))
    y = bay
    racks = []
    while y + depth < H - 1.5:
        racks.append(y)
        walls += _box(x0, y, x1, y + depth, refl=rack_refl)
        step = rng.uniform(2.4, 3.0)
        for x in np.arange(x0, x1 + 1e-9, step):  # uprights stand proud of the rack faces
            for yy in (y - 0.05, y + depth + 0.05):
                circles.append(CircleSpec(centre=(float(x), float(yy)), radius=0.04, reflectivity=0.9))
        y += depth + aisle
    pitch = rng.uniform(5.0, 8.0)
    for px in np.arange(pitch / 2, W - 1.0, pitch):
        circles.append(CircleSpec(centre=(float(px), float(bay / 2)), radius=float(rng.uniform(0.2, 0.35))))
    for _ in range(int(rng.integers(3, 8))):
        for _try in range(20):
            cx, cy = rng.uniform(1.2, W - 1.2), rng.uniform(0.9, bay - 0.9)
            if _clear_of(walls, circles, (cx, cy), 1.3):
                walls += _rotated_box(cx, cy, 1.2, 0.8, rng.uniform(0, math.pi), refl=float(rng.uniform(0.5, 0.9)))
                break
    spawn = [SpawnBox(x=(1.0, W - 1.0), y=(0.6, bay - 0.6))]
    spawn += [SpawnBox(x=(x0 + 0.5, x1 - 0.5), y=(r + depth + 0.5, r + depth + aisle - 0.5)) for r in racks[:-1]]
    return World.from_spec(WorldSpec(name=f"warehouse-{seed}", walls=walls, circles=circles, spawn=spawn))


def rooms_world(seed: int = 0) -> World:
    """A floor of rooms: an outer shell with cut (angled) corners, slanted partitions with doors,
    furniture boxes at any angle and table legs."""
    rng = np.random.default_rng(seed)
    W, H = rng.uniform(8.0, 14.0), rng.uniform(6.0, 10.0)
    refl = float(rng.uniform(0.7, 1.0))
    cut = rng.uniform(0.5, 2.0, 4) * (rng.random(4) < 0.6)  # corner chamfers: angled walls
    corners = [(0, 0), (W, 0), (W, H), (0, H)]
    shell = []
    for i, (cx, cy) in enumerate(corners):
        px, py = corners[i - 1]
        nx, ny = corners[(i + 1) % 4]
        c = cut[i]
        if c > 0:
            shell.append((cx + c * np.sign(px - cx), cy + c * np.sign(py - cy)))
            shell.append((cx + c * np.sign(nx - cx), cy + c * np.sign(ny - cy)))
        else:
            shell.append((cx, cy))
    walls = [WallSpec(start=shell[i], end=shell[(i + 1) % len(shell)], reflectivity=refl) for i in range(len(shell))]
    # Partitions across the floor, slanted, each with a door; they split it into rooms.
    n_part = int(rng.integers(1, 4))
    edges = np.sort(rng.uniform(0.25, 0.75, n_part)) if n_part == 1 else np.linspace(0, 1, n_part + 2)[1:-1]
    xs = []
    for e in edges:
        xa = e * W + rng.uniform(-0.8, 0.8)
        xb = xa + rng.uniform(-1.5, 1.5)
        xs.append((xa, xb))
        door, d0 = rng.uniform(0.8, 1.2), rng.uniform(0.2, 0.8 - 0.15)
        t0, t1 = d0, d0 + door / H
        a, b = np.array([xa, 0.0]), np.array([xb, H])
        for lo, hi in ((0.0, t0), (t1, 1.0)):
            walls.append(WallSpec(start=tuple(a + lo * (b - a)), end=tuple(a + hi * (b - a)), reflectivity=refl))
    circles: list[CircleSpec] = []
    bounds = [0.0] + [max(xa, xb) for xa, xb in xs] + [W]
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        for _ in range(int(rng.integers(1, 3))):
            for _try in range(20):
                cx, cy = rng.uniform(lo + 0.8, max(lo + 0.9, hi - 0.8)), rng.uniform(1.0, H - 1.0)
                if _clear_of(walls, circles, (cx, cy), 1.0):
                    walls += _rotated_box(cx, cy, rng.uniform(0.4, 1.2), rng.uniform(0.3, 0.7), rng.uniform(0, math.pi),
                                          refl=float(rng.uniform(0.5, 0.9)))
                    break
        if rng.random() < 0.7:
            tx, ty = rng.uniform(lo + 0.6, max(lo + 0.7, hi - 1.6)), rng.uniform(0.8, H - 1.6)
            for dx, dy in ((0, 0), (0.9, 0), (0, 0.6), (0.9, 0.6)):
                circles.append(CircleSpec(centre=(tx + dx, ty + dy), radius=0.025, reflectivity=0.6))
    m = float(cut.max()) + 0.4
    spawn = [SpawnBox(x=(m, W - m), y=(m, H - m))]
    return World.from_spec(WorldSpec(name=f"rooms-{seed}", walls=walls, circles=circles, spawn=spawn))


#: The built-in families by name: seed -> World.
FAMILIES: dict[str, Callable[[int], World]] = {
    "lab": lab_world, "corridor": corridor_family, "orchard": orchard_world,
    "warehouse": warehouse_world, "rooms": rooms_world,
}


#: The largest world file read: walls and circles by the hundred thousand fit in far less.
MAX_WORLD_BYTES = 16 * 2**20


def load_world(name_or_path: str, seed: int = 0) -> World:
    """A built-in world family's variant ``seed`` (``families.FAMILIES``) or a JSON/TOML world file."""
    if name_or_path in FAMILIES:
        return FAMILIES[name_or_path](seed)
    path = Path(name_or_path)
    if not path.is_file():
        raise SonarSetError(f"{name_or_path}: not a built-in world family ({', '.join(FAMILIES)}) nor a world file")
    if path.stat().st_size > MAX_WORLD_BYTES:
        raise SonarSetError(f"{path}: {path.stat().st_size / 2**20:.0f} MiB is not a world file "
                            f"(the limit is {MAX_WORLD_BYTES // 2**20} MiB)")
    try:
        text = path.read_text()
        if path.suffix == ".toml":
            import tomllib

            doc = tomllib.loads(text)
        else:
            doc = json.loads(text)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise SonarSetError(f"{path}: cannot parse world file ({exc})") from None
    except RecursionError:
        raise SonarSetError(f"{path}: cannot parse world file (nested too deeply)") from None
    try:
        return World.from_spec(WorldSpec.model_validate(doc))
    except ValidationError as exc:
        raise SonarSetError(f"{path}: {pydantic_problems(exc)[0]}") from None
    except RecursionError:
        raise SonarSetError(f"{path}: not a world file (nested too deeply)") from None
