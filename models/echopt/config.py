"""EchoPT's configuration: the network's sizes, its presets and priors, and the grid and robot it is
built for. No torch here: the command line lists the presets and priors without loading it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from sonarset.errors import GridMismatchError
from sonarset.format.attrs import RobotRig, SensorGrid
from sonarset.windows import N_IN

#: The robot a config describes when no store's rig is given (the record's defaults: the simulator's).
_DEFAULT_RIG = RobotRig()
#: The grid a config describes when none is given: the format's default.
_DEFAULT_GRID = SensorGrid.default()


class ConfigError(ValueError):
    """A setting no network can have; ``setting`` names it (a caller maps it to its own option)."""

    def __init__(self, setting: str, message: str):
        super().__init__(message)
        self.setting = setting


def check_rig_and_inputs(cfg) -> None:
    """The checks every network's config shares (EchoPT's and the reference methods'): the rig's
    numbers, the grid's edges, the prior and the inputs; ConfigError naming the first bad one."""
    for name in ("dt", "sensor_offset"):
        v = getattr(cfg, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ConfigError(name, f"{name} must be a finite number, got {v!r}")
    if cfg.dt <= 0:
        raise ConfigError("dt", f"dt (the frame interval) must be > 0 s, got {cfg.dt}")
    for name in ("range_edges", "azimuth_edges"):
        lo_hi = getattr(cfg, name)
        if not (isinstance(lo_hi, tuple) and len(lo_hi) == 2 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in lo_hi)
                and lo_hi[0] < lo_hi[1]):
            raise ConfigError(name, f"{name} must be two finite increasing numbers, got {lo_hi!r}")
    if cfg.prior not in PRIORS:
        raise ConfigError("prior", f"prior must be one of {', '.join(PRIORS)}, got {cfg.prior!r}")
    if cfg.inputs not in INPUTS:
        raise ConfigError("inputs", f"inputs must be one of {', '.join(INPUTS)}, got {cfg.inputs!r}")


def config_fields(cls, d: dict) -> dict:
    """The keyword arguments of config class ``cls`` in a card's ``config`` dict (JSON lists back to
    tuples; keys the class does not have are left out)."""
    names = {f.name for f in fields(cls)}
    return {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in names}


@dataclass(frozen=True)
class EchoPTConfig:
    n_range: int = _DEFAULT_GRID.n_range
    n_azimuth: int = _DEFAULT_GRID.n_azimuth
    n_in: int = N_IN  # input frames: the paper's window
    patch: tuple[int, int] = (25, 5)
    d_embed: int = 376  # image part of a token; + 2 (n_in + 1) command values = d_model
    n_layers: int = 8
    n_heads: int = 6
    d_ff: int = 500
    max_tokens: int = 2000  # the paper's positional table (376 x 2000); the grid uses the first ones
    kernel: tuple[int, int] = (20, 5)
    tf_channels: tuple[int, int] = (16, 32)  # convolutions after un-embedding
    frame_channels: int = 16  # convolutional branch over the frame stack
    head_channels: tuple[int, int] = (16, 4)  # output stack: (65 -> 16 -> 4 -> 1 for the paper)
    mlp_hidden: int = 10
    mlp_out: int = 200  # laid out as a 20 x 10 image
    prior: str = "none"  # none (paper) | last | flow: the image the output corrects
    # raw (paper): the frames as measured | aligned: each warped to the predicted frame's pose along
    # the window's commands (the flow of each frame), so every branch sees the frames registered
    inputs: str = "raw"
    # Channels of the geometry-modulated correction (0: none, the paper's). Convolutions are blind to
    # where a pixel lies, but how a warp misplaces an echo depends on it: the azimuth PSF is
    # shift-invariant in sin(azimuth), so an echo turned towards the edge widens in azimuth, and near
    # echoes move fastest. This branch adds sum_k m_k(pixel, command) x f_k(frames): linear filters of
    # the frames weighted per pixel by an MLP of the pixel's position and the newest command's warp.
    geometry_channels: int = 0
    dropout: float = 0.0
    # The sensor grid's edges and the robot rig, which the flow prior needs (from the store).
    range_edges: tuple[float, float] = (_DEFAULT_GRID.range_min_m, _DEFAULT_GRID.range_max_m)
    azimuth_edges: tuple[float, float] = (_DEFAULT_GRID.azimuth_min_rad, _DEFAULT_GRID.azimuth_max_rad)
    dt: float = _DEFAULT_RIG.frame_interval_s
    sensor_offset: float = _DEFAULT_RIG.sensor_offset_m

    @property
    def n_cmd(self) -> int:
        return 2 * (self.n_in + 1)

    @property
    def d_model(self) -> int:
        return self.d_embed + self.n_cmd

    @property
    def grid_tokens(self) -> tuple[int, int]:
        return self.n_range // self.patch[0], self.n_azimuth // self.patch[1]

    def check(self) -> None:
        """ConfigError (GridMismatchError for the grid) naming the first setting no network can have:
        a model card is data from a file, and a bad one must fail here, not deep in torch."""
        sizes = {"n_range": self.n_range, "n_azimuth": self.n_azimuth, "n_in": self.n_in, "d_embed": self.d_embed,
                 "n_layers": self.n_layers, "n_heads": self.n_heads, "d_ff": self.d_ff,
                 "max_tokens": self.max_tokens, "frame_channels": self.frame_channels,
                 "mlp_hidden": self.mlp_hidden, "mlp_out": self.mlp_out}
        pairs = {"patch": self.patch, "kernel": self.kernel, "tf_channels": self.tf_channels,
                 "head_channels": self.head_channels}
        for name, pair in pairs.items():
            if not (isinstance(pair, tuple) and len(pair) == 2):
                raise ConfigError(name, f"{name} must be a pair of integers, got {pair!r}")
            sizes.update({f"{name}[{i}]": v for i, v in enumerate(pair)})
        for name, v in sizes.items():
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= _MAX_SIZE.get(name, 100_000):
                raise ConfigError(name.split("[")[0],
                                  f"{name} must be an integer in 1..{_MAX_SIZE.get(name, 100_000)}, got {v!r}")
        check_rig_and_inputs(self)
        d = self.dropout
        if isinstance(d, bool) or not isinstance(d, (int, float)) or not 0 <= d < 1:
            raise ConfigError("dropout", f"dropout must be in [0, 1), got {d!r}")
        if self.n_range % self.patch[0] or self.n_azimuth % self.patch[1]:
            raise GridMismatchError(f"grid {self.n_range}x{self.n_azimuth} is not divisible by the "
                                    f"{self.patch[0]}x{self.patch[1]} patch")
        g = self.geometry_channels
        if isinstance(g, bool) or not isinstance(g, int) or not 0 <= g <= 1024:
            raise ConfigError("geometry_channels", f"geometry_channels must be an integer in 0..1024, got {g!r}")
        if self.grid_tokens[0] * self.grid_tokens[1] > self.max_tokens:
            raise GridMismatchError(f"grid {self.n_range}x{self.n_azimuth} needs more than {self.max_tokens} tokens")
        if self.d_model % self.n_heads:
            raise ConfigError("d_model", f"d_model {self.d_model} is not divisible by {self.n_heads} heads")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "EchoPTConfig":
        kw = config_fields(cls, d)
        if "prior" not in d and "residual" in d:  # cards before the prior option: residual = last frame
            kw["prior"] = "last" if d["residual"] else "none"
        return cls(**kw)


PRIORS = ("none", "last", "flow")
INPUTS = ("raw", "aligned")
#: Settings a fine-tune (``init``) may change: how the inputs are prepared, and EchoWarp's ``outside``
#: (what its warp reads outside the view); none changes a weight's shape or meaning enough to forbid
#: starting from a trained model (the card's lineage records the change).
WARM_START_FIELDS = ("inputs", "outside")
#: A fine-tune may also add the geometry branch to a model without one: it starts at zero, so the
#: new model starts as the trained one.
ADDABLE_FIELDS = ("geometry_channels",)
# Upper bounds on a card's sizes, far above any network here (the paper's: 8 layers, 376 + 8 wide,
# 2000 tokens) but below what would exhaust memory building one; unlisted sizes: 100,000.
_MAX_SIZE = {"n_layers": 256, "n_heads": 256, "n_in": 64, "d_embed": 8192, "d_ff": 32768, "max_tokens": 100_000,
             "frame_channels": 1024, "mlp_hidden": 4096, "tf_channels[0]": 1024, "tf_channels[1]": 1024,
             "head_channels[0]": 1024, "head_channels[1]": 1024}


#: In the order the command line lists them: the default first.
PRESETS: dict[str, dict] = {
    # Sized by measurement to train on a 2-core CPU (BENCHMARKS.md): 0.62 M parameters, ~50
    # samples/s. Full-resolution 20 x 5 convolutions cost most of the paper model's time on a CPU,
    # so the small preset uses 5 x 3 kernels and 8 channels, and predicts a correction to a prior
    # (default: the acoustic-flow warp of the last frame), which starts training from that
    # prior's accuracy instead of from zero.
    "small": dict(d_embed=120, n_layers=4, n_heads=4, d_ff=256, max_tokens=144, kernel=(5, 3),
                  tf_channels=(4, 8), frame_channels=8, head_channels=(8, 4), prior="flow"),
    # The paper's model: ~9 M parameters, ~7.8 M of them in the 8 transformer blocks.
    "paper": {},
    # For tests and smoke runs on tiny grids: seconds per hundred steps.
    "tiny": dict(d_embed=24, n_layers=2, n_heads=2, d_ff=32, max_tokens=64, kernel=(3, 3),
                 tf_channels=(2, 4), frame_channels=4, head_channels=(4, 2), mlp_hidden=8, mlp_out=50,
                 prior="flow"),
}


def make_config(preset: str, n_range: int = _DEFAULT_GRID.n_range, n_azimuth: int = _DEFAULT_GRID.n_azimuth,
                **overrides) -> EchoPTConfig:
    """A preset's config on an ``n_range`` x ``n_azimuth`` grid; ``overrides`` set any field
    (``prior``, the grid's edges and the rig for the flow prior: :func:`grid_and_rig` makes them)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
    cfg = EchoPTConfig(n_range=n_range, n_azimuth=n_azimuth, **{**PRESETS[preset], **overrides})
    cfg.check()
    return cfg


def grid_and_rig(grid, rig=None) -> dict:
    """Config fields for a store's grid (a SensorGrid) and robot rig (a RobotRig, or None: the
    simulator's), which the flow prior needs."""
    out = {"range_edges": (grid.range_min_m, grid.range_max_m), "azimuth_edges": (grid.azimuth_min_rad, grid.azimuth_max_rad)}
    if rig is not None:
        out.update(dt=rig.frame_interval_s, sensor_offset=rig.sensor_offset_m)
    return out
