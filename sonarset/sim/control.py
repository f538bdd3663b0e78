"""Sonar-driven robot control: acoustic-flow regions, a subsumption controller and a burst detector.

The controller follows Steckel & Peremans, "Acoustic flow-based control of a mobile platform using
a 3D sonar sensor" (IEEE Sensors J., 2017) and the EchoPT paper's corridor experiment. For a robot
driving forward, a static reflector at (r, θ) in the sensor frame moves along the flow line
y = r sin θ = const (its lateral offset) while its forward distance x = r cos θ shrinks at the
speed of the robot. Regions of the energyscape defined on (x, y) therefore carry meaning without
any object segmentation:

- the *frontal* region, |y| below the robot's half-width: whatever is there will be hit; its
  nearest echo over the speed is the time to contact;
- the two *lateral* regions, left and right flow lines out to a corridor's width: the energy-
  weighted lateral offset of each side says how far the corridor walls (or rows of poles) are.

Three layers, higher ones subsuming lower ones (Brooks 1986): collision avoidance over corridor
following over goal seeking. Gains are the fields of :class:`ControllerGains`, documented there.
The controller sees only images and its odometry; it knows nothing of noise bursts.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from sonarset.format.attrs import Processing, SensorGrid


@dataclass(frozen=True)
class ControllerGains:
    """Every number the controller uses (SI units).

    Frontal obstacles are pixels above ``echo_level`` (0.3 is -42 dB re full scale, 13 dB above the
    simulator's -55 dB noise floor, so that sensor noise alone almost never crosses it). The lateral
    balance weighs pixels by their linear energy, 10^(60 dB (p - 1) / 10), above that of
    ``lateral_level``; a soft threshold, so that forecasts whose peaks are smoothed (a regression
    model's conditional mean) still balance like the images they forecast.
    """

    v_cruise: float = 0.3  # m/s, forward speed when the way is clear
    w_max: float = 1.0  # rad/s, turn-rate limit (the robot's)
    echo_level: float = 0.3  # pixel value above which a frontal pixel is an obstacle
    lateral_level: float = 0.25  # pixel value (-45 dB, 10 dB above the noise floor) whose energy
    # is subtracted from every lateral pixel: the energy balance weighs what stands out of the noise
    look_ahead: float = 2.5  # m, forward extent x of the lateral and frontal regions
    half_width: float = 0.3  # m, frontal region |y| < half_width (robot radius 0.2 m + 0.1 m)
    sidelobe_db: float = 10.0  # a frontal pixel this far below the strongest echo at its range is
    # a side lobe of that echo, not an obstacle (the eRTIS array's side lobes peak at -12.4 dB)
    lateral_max: float = 1.5  # m, lateral regions half_width < |y| < lateral_max
    k_corridor: float = 2.0  # rad/s per unit of lateral imbalance (d_L - d_R) / (d_L + d_R)
    k_goal: float = 1.0  # rad/s per rad of bearing error to the waypoint
    stop_distance: float = 0.7  # m (sensor frame; the sensor sees from 0.5 m): stop and turn away
    slow_distance: float = 1.2  # m, frontal echoes closer than this slow the robot down linearly
    min_lateral_energy: float = 1e-7  # energy above the lateral level a side needs to count as seen

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Decision:
    v: float
    w: float
    layer: str  # "avoid", "corridor" or "goal": which layer produced the command


class FlowRegions:
    """Pixel geometry of a sensor grid in the sensor frame: forward x and lateral y (flow lines)."""

    def __init__(self, grid: SensorGrid, gains: ControllerGains):
        r = grid.range_centres()[:, None]
        th = grid.azimuth_centres()[None, :]
        self.x, self.y = r * np.cos(th), r * np.sin(th)
        ahead = (self.x > 0) & (self.x < gains.look_ahead)
        self.front = ahead & (np.abs(self.y) < gains.half_width)
        self.left = ahead & (self.y >= gains.half_width) & (self.y < gains.lateral_max)
        self.right = ahead & (self.y <= -gains.half_width) & (self.y > -gains.lateral_max)


class SubsumptionController:
    """Image + odometry pose -> (v, ω) command; see the module docstring."""

    def __init__(self, grid: SensorGrid, waypoint: tuple[float, float], gains: ControllerGains | None = None,
                 dynamic_range_db: float = Processing.model_fields["span_db"].default):
        self.gains = gains or ControllerGains()
        self.regions = FlowRegions(grid, self.gains)
        self.waypoint = np.asarray(waypoint, float)
        self.dr = dynamic_range_db

    def energy(self, image: np.ndarray) -> np.ndarray:
        """Linear energy re full scale of every pixel."""
        return 10 ** (self.dr * (np.asarray(image, np.float64) - 1) / 10)

    def lateral_distances(self, e: np.ndarray) -> tuple[float, float]:
        """Energy-weighted lateral offset of the echoes on the left and on the right; a side with
        nothing above the lateral level is as far as the region reaches."""
        g, reg = self.gains, self.regions
        floor = 10 ** (self.dr * (g.lateral_level - 1) / 10)
        out = []
        for mask in (reg.left, reg.right):
            w = np.maximum(e[mask] - floor, 0.0)
            total = w.sum()
            out.append(float((w * np.abs(reg.y[mask])).sum() / total) if total > g.min_lateral_energy else g.lateral_max)
        return out[0], out[1]

    def corridor_turn(self, e: np.ndarray) -> float | None:
        """The corridor layer's turn rate (before the rate limit) for the pixel energies ``e``: the
        lateral distances balanced; None when neither side holds an echo (the layer passes)."""
        g = self.gains
        d_left, d_right = self.lateral_distances(e)
        if d_left < g.lateral_max or d_right < g.lateral_max:
            return g.k_corridor * (d_left - d_right) / (d_left + d_right)
        return None

    def __call__(self, image: np.ndarray, pose: np.ndarray) -> Decision:
        g, reg = self.gains, self.regions
        e = self.energy(image)
        # Layer 3, collision avoidance: the nearest echo on the frontal flow lines.
        img = np.asarray(image)
        main_lobe = img >= img.max(axis=1, keepdims=True) - g.sidelobe_db / self.dr
        front = ((img > g.echo_level) & main_lobe)[reg.front]
        nearest = float(reg.x[reg.front][front].min()) if front.any() else np.inf
        if nearest < g.stop_distance:
            # turn in place towards the side with less frontal energy
            left = e[reg.front & (reg.y > 0)].sum()
            right = e[reg.front & (reg.y < 0)].sum()
            return Decision(0.0, -g.w_max if left > right else g.w_max, "avoid")
        v = g.v_cruise * float(np.clip((nearest - g.stop_distance) / (g.slow_distance - g.stop_distance), 0.0, 1.0))
        # Layer 2, corridor following: balance the lateral distances along the flow lines.
        w = self.corridor_turn(e)
        if w is not None:
            return Decision(v, float(np.clip(w, -g.w_max, g.w_max)), "corridor")
        # Layer 1, goal seeking on odometry.
        dx, dy = self.waypoint - pose[:2]
        bearing = (np.arctan2(dy, dx) - pose[2] + np.pi) % (2 * np.pi) - np.pi
        return Decision(v, float(np.clip(g.k_goal * bearing, -g.w_max, g.w_max)), "goal")


@dataclass(frozen=True)
class BurstDetector:
    """Flags frames swamped by broadband noise from the image alone.

    Echoes arrive from reflectors, at a few discrete ranges; broadband noise arrives all the time,
    so it reaches every range bin. A frame in which more than ``max_coverage`` of the range bins hold
    a pixel above ``level`` is a burst. The feature survives the energyscape post-processing: the
    'ertis' profile subtracts 1.5x each range row's azimuth mean, which turns a burst's uniform
    level into a few bright blobs (~8% of the pixels above 0.5, so a pixel count misses it), but
    every row keeps its blobs. Measured on 1000 random poses per world (``bench/bench_burst.py``):
    clean frames cover at most 0.03 / 0.10 (corridor, raw / ertis) and 0.21 / 0.40 (lab, facing
    cluttered walls) of the range bins; -80 dB bursts cover 0.89-1.0 (ertis) and 1.0 (raw).

    What it cannot see: the simulator sets a burst's noise 80 dB above the frame's strongest echo
    (the paper's SNR), so with only weak echoes in view (a robot turned out of the corridor) a burst
    stays near or under the -60 dB floor and the frame looks almost empty. Over poses anywhere
    around the corridor, facing any way, the detector flags 74% of ertis bursts and 90% of raw ones
    (raw: the frames with no echo in view at all); inside the corridor, all of them.
    """

    level: float = 0.5
    max_coverage: float = 0.6

    def coverage(self, image: np.ndarray) -> float:
        """Fraction of range bins (rows) with a pixel above ``level``."""
        return float((np.asarray(image) > self.level).any(axis=-1).mean())

    def __call__(self, image: np.ndarray) -> bool:
        return self.coverage(image) > self.max_coverage
