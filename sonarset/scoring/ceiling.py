"""The noise ceiling: target frames of simulated runs re-rendered with an independent noise draw.

A simulated run records its world (``source``) and the robot's true poses (``pose``), so any of
its frames can be rendered again from the same scene with fresh sensor noise. Scoring a target
frame against such a re-render measures how much of the image is predictable at all: no predictor,
however good, knows the target's noise draw. Evaluation with the ceiling reports it as the method
``ceiling`` (the same at every horizon: the re-render of the target itself).

The observable ceiling (``OBSERVABLE``) asks what a predictor could know from a window's
context: each target frame is re-rendered at its true pose from only the reflectors that produced
an echo in the window's context frames (the heard stretches of walls, at the simulator's wall
sampling, and the heard circles), with independent noise. An echo counts as heard when it
reached the image's display range (``observed_world``). Reflectors never heard neither echo nor
occlude in the re-render. The noise ceiling minus the observable ceiling is what enters the view during a
rollout: no predictor from this context can know it.

Runs that cannot be re-rendered (imported recordings, runs without poses or simulator provenance,
a world file no longer on disk, unknown image processing) raise :class:`CeilingUnavailable` with
a one-line reason. This module does not import torch.
"""

from __future__ import annotations

import copy
import zlib

import numpy as np

from sonarset.errors import SonarSetError
from sonarset.store.store import SonarStore

CEILING = "ceiling"
OBSERVABLE = "observable"
#: The rows of ``eval --ceiling``: references, not predictors.
CEILINGS = (CEILING, OBSERVABLE)
#: Spawn-key tags of the ceilings' noise streams: with the eval seed as entropy, they are
#: independent of every stream the simulator drew the recorded frames from, and of each other.
_STREAM_TAG = 0x6365696C  # "ceil"
OBSERVABLE_STREAM = 0x6F627376  # "obsv"
_NEEDS = ("world", "world_seed", "snr_db")


class CeilingUnavailable(SonarSetError):
    """A run cannot be re-rendered; the message is the one-line reason."""


def _store_processing(store: SonarStore):
    """The store's image processing (``sonarset.format.attrs.Processing``), or None when unknown."""
    proc = getattr(store, "processing", None)
    if proc is None or getattr(proc, "profile", None) == "unknown":
        return None
    return proc


class RunRenderer:
    """Renders frames of one simulated run again, from its recorded world and poses.

    Raises :class:`CeilingUnavailable` when the run cannot be re-rendered. ``render`` draws the
    noise from one generator per run seeded by ``seed`` (e.g. the eval seed) and the run's name:
    the same seed and the same sequence of calls give the same images, whatever the batch size.
    """

    def __init__(self, store: SonarStore, name: str, seed: int = 0, stream: int = _STREAM_TAG):
        from sonarset.sim.sonar import SonarModel
        from sonarset.sim.families import load_world

        run = store.run(name)
        src = dict(run.attrs.source or {})
        kind = src.get("kind")
        if kind != "simulator":
            raise CeilingUnavailable("an imported recording, not a simulated run" if kind == "import"
                                     else f"no simulator provenance (source kind {kind or 'missing'})")
        if not run.has("pose"):
            raise CeilingUnavailable("no recorded poses (no 'pose' array)")
        missing = [k for k in _NEEDS if k not in src]
        if missing:
            raise CeilingUnavailable(f"its provenance lacks {', '.join(missing)}")
        try:
            self.world = load_world(str(src["world"]), int(src["world_seed"]))
        except SonarSetError as exc:
            raise CeilingUnavailable(f"world cannot be rebuilt: {exc}") from None
        except (TypeError, ValueError) as exc:
            raise CeilingUnavailable(f"world seed {src['world_seed']!r} is not an integer ({exc})") from None
        proc = _store_processing(store)
        if proc is None:
            raise CeilingUnavailable("the store's image processing is unknown")
        try:
            self.model = SonarModel(store.grid, snr_db=float(src["snr_db"]), psf=str(src.get("psf", "array")),
                                    processing=proc)
        except (TypeError, ValueError) as exc:
            raise CeilingUnavailable(f"cannot build its sonar model ({exc})") from None
        self.name = name
        self.poses = np.asarray(run.read("pose"), float)  # checked: a corrupt pose is refused, not rendered
        self.image_dtype = run.images.dtype
        self.shape = store.grid.shape
        self._seed = int(seed) & (2 ** 128 - 1)
        self.rng = np.random.Generator(np.random.SFC64(np.random.SeedSequence(
            self._seed, spawn_key=(stream, zlib.crc32(name.encode())))))

    def render(self, frames: np.ndarray) -> np.ndarray:
        """Frames ``frames`` (indices into the run) rendered again with fresh noise: float32
        (F, R, A), rounded through the run's image dtype as the recorded frames were.

        Every frame is re-rendered at the run's nominal SNR (``source.snr_db``), burst frames
        included: a burst is noise of the target frame, which no predictor can know, while the
        re-render stands for the best prediction of the scene. (The recorded ``snr_db`` array is
        each frame's effective SNR, which also moves with the noise floor; it is not re-used.)
        The true poses are recorded, so wheel slip plays no part.
        """
        frames = np.asarray(frames, np.int64)
        out = np.empty((len(frames), *self.shape), self.image_dtype)
        if len(frames):
            self.model.render_batch(self.world, self.poses[frames], self.rng, out=out)
        return out.astype(np.float32, copy=False)


    def with_stream(self, stream: int) -> "RunRenderer":
        """The same run's renderer with its own noise stream ``stream`` (the world, poses and
        sonar model shared, not rebuilt)."""
        other = copy.copy(self)
        other.rng = np.random.Generator(np.random.SFC64(np.random.SeedSequence(
            self._seed, spawn_key=(stream, zlib.crc32(self.name.encode())))))
        return other

    def render_observed(self, context: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Frames ``frames`` re-rendered from only what the run's frames ``context`` heard (the
        observable ceiling), with fresh noise: float32 (F, R, A) as ``render``."""
        frames = np.asarray(frames, np.int64)
        out = np.empty((len(frames), *self.shape), self.image_dtype)
        if len(frames):
            world = observed_world(self.world, self.model, self.poses[np.asarray(context, np.int64)])
            self.model.render_batch(world, self.poses[frames], self.rng, out=out)
        return out.astype(np.float32, copy=False)


def observed_world(world, model, poses: np.ndarray):
    """The part of ``world`` that produced an echo in frames seen from the robot poses ``poses``
    (F, 3): every reflector point in the sonar's view, in range and unoccluded, whose echo reaches
    the image's display range (``model.dynamic_range_db`` below a perfect wall at the minimum
    range); heard stretches of walls (runs of heard samples, each standing for its ``WALL_STEP``)
    and heard circles, as a new World.

    Not "above the sensor noise": the beamformer, the coherence factor and the smoothing lift
    echoes below one frame's noise std into the image (a threshold there left the ceiling below
    flow at one-shot, CC 0.93 against 0.96 on a lab run; at the display floor 0.97-0.98)."""
    from sonarset.sim.robot import sensor_pose
    from sonarset.sim.sonar import WALL_STEP, visible_echoes
    from sonarset.sim.world import World

    echoes = visible_echoes(world, sensor_pose(poses), model.grid.range_max_m + 0.1)
    n_walls = len(world.seg_a)
    heard = echoes.amp >= np.sqrt(model.e_full) * 10 ** (-model.dynamic_range_db / 20)
    src, along = echoes.source[heard], echoes.along[heard]
    starts, ends, refl = [], [], []
    for j in np.unique(src[src < n_walls]):
        t = np.unique(np.round(along[src == j] / WALL_STEP * 2) / 2 * WALL_STEP)  # samples of several frames
        breaks = np.flatnonzero(np.diff(t) > 1.5 * WALL_STEP)
        a, b = world.seg_a[j], world.seg_b[j]
        u = (b - a) / np.linalg.norm(b - a)
        for lo, hi in zip(np.r_[0, breaks + 1], np.r_[breaks, len(t) - 1]):
            starts.append(a + (t[lo] - WALL_STEP / 2) * u)
            ends.append(a + (t[hi] + WALL_STEP / 2) * u)
            refl.append(world.seg_refl[j])
    circles = np.unique(src[src >= n_walls]) - n_walls
    return World(f"{world.name} (observed)", np.array(starts, float).reshape(-1, 2), np.array(ends, float).reshape(-1, 2),
                 np.array(refl, float), world.circ_c[circles].reshape(-1, 2), world.circ_r[circles], world.circ_refl[circles])


def rerender(store: SonarStore, name: str, frames: np.ndarray, seed: int = 0, batch_size: int = 64) -> np.ndarray:
    """Frames ``frames`` of run ``name`` re-rendered with independent noise (see :class:`RunRenderer`)."""
    r = RunRenderer(store, name, seed)
    frames = np.asarray(frames, np.int64)
    parts = [r.render(frames[lo:lo + batch_size]) for lo in range(0, len(frames), batch_size)]
    return np.concatenate(parts) if parts else np.empty((0, *r.shape), np.float32)
