"""What a store of simulated runs holds (``GenerationSpec``), checked once.

Light on purpose (no simulator, no numba): the command line reads its defaults for its help.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from sonarset.errors import SonarSetError
from sonarset.format.attrs import Processing, SensorGrid
from sonarset.sensor.ertis import AZIMUTH_PSFS

DT = 0.2  # s, 5 Hz frames
#: Training runs of a single world when ``runs`` is not given (the paper's ten runs).
DEFAULT_RUNS = 10
#: The images a store gets unless told otherwise: the sensor toolchain's.
DEFAULT_PROCESSING = "ertis"


def check_psf(psf: str, processing: Processing) -> None:
    """ValueError unless the azimuth PSF ``psf`` can be used with ``processing``."""
    if psf not in AZIMUTH_PSFS:
        raise ValueError(f"psf must be one of {', '.join(AZIMUTH_PSFS)}, got {psf!r}")
    if processing.beamformer != "das" and psf != "array":
        raise ValueError(f"psf {psf!r} is a delay-and-sum ablation; it needs a 'das' beamformer "
                         f"(processing {processing.profile!r} uses {processing.beamformer!r})")


def world_mix(world: str, runs: int | None = None) -> list[tuple[str, int]]:
    """The (world, training runs) pairs of a ``world`` value.

    A single world takes ``runs`` (default ``DEFAULT_RUNS``); a mix names each world's count, ``lab:4,orchard:2``
    (built-in families or world files, in order), and then ``runs`` must not be given.
    """
    entries = [e.strip() for e in world.split(",") if e.strip()]
    if not entries:
        raise SonarSetError("world is empty; give a world family (lab) or a mix (lab:4,orchard:2)", parameter="world")
    mix = []
    for entry in entries:
        name, sep, count = entry.rpartition(":")
        if sep and count.strip().isdigit() and name.strip():
            mix.append((name.strip(), int(count)))
        else:
            mix.append((entry, None))
    counted = [n is not None for _, n in mix]
    if any(counted) and not all(counted):
        raise SonarSetError(f"world {world!r}: give every world a run count (lab:4,orchard:2) or none",
                            parameter="world")
    if not any(counted):
        if len(mix) > 1:
            raise SonarSetError(f"world {world!r}: several worlds need a run count each (lab:4,orchard:2)",
                                parameter="world")
        return [(mix[0][0], DEFAULT_RUNS if runs is None else runs)]
    if runs is not None:
        raise SonarSetError(f"world {world!r} gives the run counts; leave runs unset", parameter="world")
    names = [name for name, _ in mix]
    if len(set(names)) < len(names):
        raise SonarSetError(f"world {world!r}: a world is named twice", parameter="world")
    return [(name, int(n)) for name, n in mix]


@dataclass(frozen=True)
class GenerationSpec:
    """What a store of simulated runs holds: the settings that decide its arrays, checked once, here.

    ``world`` is a world family or file with ``runs`` training runs (default ``DEFAULT_RUNS``), or a mix that
    counts each world's runs (``runs`` then stays None); each world also gets ``test_runs`` test
    runs of ``minutes`` each. ``processing`` is a profile name or ``Processing`` settings (held as
    settings); ``psf`` the azimuth PSF, which must suit the processing's beamformer. Invalid
    settings raise SonarSetError with a one-line reason.
    """

    runs: int | None = None
    test_runs: int = 1
    minutes: float = 25.0
    seed: int = 0
    world: str = "lab"
    snr_db: float = 5.0
    psf: str = "array"
    processing: Processing = field(default_factory=lambda: Processing.named(DEFAULT_PROCESSING))
    grid: SensorGrid = field(default_factory=SensorGrid.default)

    def __post_init__(self) -> None:
        mix = self.world_mix()
        if isinstance(self.processing, str):
            try:
                object.__setattr__(self, "processing", Processing.named(self.processing))
            except ValueError as exc:
                raise SonarSetError(str(exc), parameter="processing") from None
        try:
            check_psf(self.psf, self.processing)
        except ValueError as exc:
            raise SonarSetError(str(exc), parameter="psf") from None
        if self.n_frames < 1:
            raise SonarSetError(f"minutes must give at least one frame at 5 Hz (got {self.minutes})",
                                parameter="minutes")
        if min(n for _, n in mix) < 0 or self.test_runs < 0 or sum(n for _, n in mix) + self.test_runs * len(mix) < 1:
            raise SonarSetError("need at least one run", parameter="runs")

    @property
    def n_frames(self) -> int:
        """Frames of every run."""
        return int(round(self.minutes * 60 / DT))

    def world_mix(self) -> list[tuple[str, int]]:
        return world_mix(self.world, self.runs)
