"""Benchmark protocol v1, frozen: which test runs are simulated from which seeds, how many windows
are drawn, at which horizons every method is scored and against which reference.

A results file records its protocol's name, version and this definition in full, so files made
on other machines compare (``compare_results``) only when they answer the same protocol. Changing
anything here makes a new version, never a new v1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sonarset.format.attrs import SensorGrid
from sonarset.sim.spec import GenerationSpec

from sonarset.models.eval.result import METRICS

PROTOCOL_NAME = "sonarset-benchmark"
#: The world families of v1: every built-in family of sonarset.sim.FAMILIES when v1 was defined.
#: A family added later joins a later version, so that v1 files keep comparing.
V1_FAMILIES = ("lab", "corridor", "orchard", "warehouse", "rooms")
#: Held-out seeds: the shipped models were trained on seed 0's runs; these seeds spawn other runs
#: in other world variants. 4242 is the families' fresh test store of README and BENCHMARKS, 2026
#: the demo's fresh run (``sonarset demo``).
FAMILIES_SEED = 4242
DEMO_SEED = 2026


@dataclass(frozen=True)
class StoreRecipe:
    """A store of test runs only (no training run): ``test_runs`` of each world of the mix ``world``
    (``generate``'s world value, every world counted 0 training runs), ``minutes`` long, planned
    from the master ``seed``. Its ``name`` is its file name in the cache."""

    name: str
    world: str
    minutes: float
    seed: int
    test_runs: int = 1

    def spec(self, protocol: "Protocol") -> GenerationSpec:
        return GenerationSpec(world=self.world, test_runs=self.test_runs, minutes=self.minutes, seed=self.seed,
                              snr_db=protocol.snr_db, psf=protocol.psf, processing=protocol.processing,
                              grid=protocol.sensor_grid())

    def to_dict(self) -> dict:
        return {"world": self.world, "test_runs": self.test_runs, "minutes": self.minutes, "seed": self.seed}


@dataclass(frozen=True)
class Dataset:
    """What one table of the benchmark scores: the test runs of ``store`` whose world family is
    ``world`` (every test run of the store where None)."""

    name: str
    store: StoreRecipe
    world: str | None
    about: str


@dataclass(frozen=True)
class Protocol:
    """Everything that decides a benchmark's numbers besides the models and the code's version.

    Every dataset is evaluated once with all models together (``evaluate``): ``samples`` windows
    drawn with ``eval_seed`` (which also seeds the bootstraps and the ceilings' noise), each method
    rolled out to the longest of ``horizons`` (or, one that forecasts each horizon directly, asked
    for ``horizons`` alone); with ``ceiling``, the noise and observable ceilings
    beside them. ``reference`` is always scored, and every other model is tested against it.
    """

    version: str
    datasets: tuple[Dataset, ...]
    samples: int
    horizons: tuple[int, ...]
    eval_seed: int = 0
    ceiling: bool = True
    reference: str = "flow"
    metrics: tuple[str, ...] = METRICS
    snr_db: float = 5.0
    psf: str = "array"
    processing: str = "ertis"
    #: The default eRTIS-like grid (docs/conventions.md), spelled out so that v1 does not follow a
    #: later change of ``SensorGrid.default``.
    grid: tuple[tuple[str, float], ...] = (("range_min_m", 0.5), ("range_max_m", 5.0), ("n_range", 200),
                                           ("azimuth_min_rad", -math.pi / 2), ("azimuth_max_rad", math.pi / 2),
                                           ("n_azimuth", 90))
    name: str = PROTOCOL_NAME

    def sensor_grid(self) -> SensorGrid:
        return SensorGrid(**dict(self.grid))

    def stores(self) -> dict[str, StoreRecipe]:
        """The protocol's stores by name, in the order the datasets first use them."""
        return {d.store.name: d.store for d in self.datasets}

    def to_dict(self) -> dict:
        """The full definition, as results files record it."""
        return {
            "name": self.name, "version": self.version, "samples": self.samples, "horizons": list(self.horizons),
            "eval_seed": self.eval_seed, "ceiling": self.ceiling, "reference": self.reference,
            "metrics": list(self.metrics),
            "images": {"snr_db": self.snr_db, "psf": self.psf, "processing": self.processing},
            "grid": dict(self.grid),
            "stores": {name: r.to_dict() for name, r in self.stores().items()},
            "datasets": [{"name": d.name, "store": d.store.name, "world": d.world, "about": d.about}
                         for d in self.datasets],
        }


def _family_datasets(store: StoreRecipe, families: tuple[str, ...]) -> tuple[Dataset, ...]:
    return tuple(Dataset(f, store, f, f"the {f} family's fresh test run ({store.minutes:g} min, master seed "
                                      f"{store.seed})") for f in families)


_V1_FAMILIES_STORE = StoreRecipe("families", ",".join(f"{f}:0" for f in V1_FAMILIES), minutes=10.0, seed=FAMILIES_SEED)
#: ``sonarset demo``'s fresh run: 25 minutes of the lab family from seed 2026 on the default grid.
_V1_DEMO_STORE = StoreRecipe("demo-lab", "lab:0", minutes=25.0, seed=DEMO_SEED)

PROTOCOL_V1 = Protocol(
    version="v1",
    datasets=(*_family_datasets(_V1_FAMILIES_STORE, V1_FAMILIES),
              Dataset("demo-lab", _V1_DEMO_STORE, None, f"the demo's fresh lab run (25 min, seed {DEMO_SEED})")),
    samples=1000,
    horizons=(1, 3, 5, 10),
)

#: ``--quick``: the same code path on a small subset, for tests and smoke runs. Its own version,
#: so that its files never compare with v1's.
PROTOCOL_V1_QUICK = Protocol(
    version="v1-quick",
    datasets=(*_family_datasets(StoreRecipe("families-quick", "lab:0,corridor:0", minutes=1.0, seed=FAMILIES_SEED),
                                ("lab", "corridor")),
              Dataset("demo-lab", StoreRecipe("demo-lab-quick", "lab:0", minutes=1.0, seed=DEMO_SEED), None,
                      f"a 1-minute lab run from the demo's seed {DEMO_SEED}")),
    samples=40,
    horizons=(1, 3),
)
