"""Where the control experiment's midline deviation comes from, closed loop (issue 51).

    python bench/bench_control_trace.py --models flow,echopt:pretrained,pretrained --runs 50

Runs the control experiment's bridged condition for each model (the same spawns, bursts and noise
as ``sonarset experiment control``) with a shadow controller: on every bridged frame it also
steers by the frame the sensor would have measured there without the burst. With y the robot's
lateral offset, "away" is sign(y) (w(forecast) - w(measured)): positive when the forecast turns
the robot further from the midline than the measurement would. Per model it prints:

- the midline deviation;
- by the frame's place in its burst (1 = the first frame bridged): the mean |w(forecast) -
  w(measured)| and the mean away;
- away over every bridged frame: the frames' mean, and the mean of each run's mean with its
  standard error over the runs (the turn rates are a few 0.01 rad/s, and the measured frame's own
  noise makes single frames' differences noisy);
- the bridged frames within 3 mm of the midline and those 2 cm or more off it: their share of the
  bridged frames, their mean away, and their share of the summed away;
- the bridged frames on which the forecast alone trips the collision-avoidance layer (a frontal
  echo nearer than the stop distance: the robot stops and turns in place at full rate), their
  mean away, in how many runs and at which frames of a run they fall, and the mean away on the
  frames 2 cm or more off the midline where
  both forecast and measurement steer by the corridor layer;
- the mean change of |y| over a burst (at the frame after it minus at its first frame).
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from sonarset.format.attrs import SensorGrid
from sonarset.models.experiments.common import parallel_map
from sonarset.models.experiments.control import Episode, run_episode
from sonarset.sim.runs import spawn_seeds


def burst_places(bridged: np.ndarray) -> np.ndarray:
    """Each frame's place in its run of bridged frames (1, 2, ...), 0 on the others."""
    place = np.zeros(len(bridged), int)
    for i, b in enumerate(bridged):
        place[i] = place[i - 1] + 1 if b and i else int(b)
    return place


def at_places(values: np.ndarray, place: np.ndarray, fmt: str) -> str:
    """The mean of ``values`` at burst frames 1, 3 and 6 ("-" where no burst is that long)."""
    return "/".join(format(values[place == k].mean(), fmt) if (place == k).any() else "-" for k in (1, 3, 6))


def band(away: np.ndarray, keep: np.ndarray) -> str:
    """The share of the frames in ``keep``, their mean away, and their share of the summed away."""
    return f"{keep.mean():.0%}, {away[keep].mean():+.4f}, {away[keep].sum() / away.sum():.0%}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="flow,echopt:pretrained,pretrained")
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0, help="the control experiment's default")
    ap.add_argument("--workers", type=int, default=None)
    args = ap.parse_args()
    grid, seeds = SensorGrid.default(), spawn_seeds(args.seed, args.runs)
    print(f"# bench_control_trace  {platform.node()}  {time.strftime('%Y-%m-%d')}  {args.runs} runs")
    print("| model | midline dev. [mm] | mean abs dw at burst frame 1/3/6 [rad/s] | away at frame 1/3/6 "
          "| away, every bridged frame: frames' mean; runs' mean (SE) | within 3 mm: frames, away, share of the sum "
          "| 2 cm or more off: frames, away, share of the sum | forecast alone trips avoidance: frames, away, where "
          "| away, 2 cm or more off, corridor layer both | abs y change over a burst [mm] |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for spec in args.models.split(","):
        t0 = time.perf_counter()
        eps = parallel_map(run_episode, [Episode(i, s, f"bursts+{spec}", grid, shadow=True)
                                         for i, s in enumerate(seeds)], args.workers)
        place, dw, away, offset, run_away, change, tripped, corridor = [], [], [], [], [], [], [], []
        trip_frames, trip_runs = [], 0  # the frames of a run at which a forecast alone trips avoidance
        for ep in eps:
            bridged = ep["predicted"]
            y = ep["pose"][:len(bridged), 1]
            at = burst_places(bridged)
            d = ep["w"] - ep["w_measured"]
            place.append(at[bridged]), dw.append(d[bridged]), away.append((np.sign(y) * d)[bridged])
            offset.append(np.abs(y[bridged]))
            tripped.append((ep["layer"] == "avoid")[bridged] & (ep["layer_measured"] != "avoid")[bridged])
            trip_frames += list(np.flatnonzero(bridged)[tripped[-1]])
            trip_runs += bool(tripped[-1].any())
            corridor.append(((ep["layer"] == "corridor") & (ep["layer_measured"] == "corridor"))[bridged])
            if bridged.any():
                run_away.append(away[-1].mean())
            starts = np.flatnonzero(at == 1)
            ends = np.flatnonzero(bridged[:-1] & ~bridged[1:]) + 1  # the first frame after each burst
            change += [abs(y[e]) - abs(y[s]) for s, e in zip(starts, ends)]
        place, dw, away, offset, tripped, corridor = (np.concatenate(a) for a in
                                                      (place, dw, away, offset, tripped, corridor))
        steady = corridor & (offset >= 0.02)

        cells = [
            f"{1000 * np.nanmean([e['midline_deviation_m'] for e in eps]):.2f}",
            at_places(np.abs(dw), place, ".3f"), at_places(away, place, "+.3f"),
            f"{away.mean():+.4f}; {np.mean(run_away):+.4f} ({np.std(run_away, ddof=1) / np.sqrt(len(run_away)):.4f})",
            band(away, offset < 0.003), band(away, offset >= 0.02),
            f"{tripped.sum()}, {away[tripped].mean():+.3f}, frames {min(trip_frames)}-{max(trip_frames)} of "
            f"{trip_runs} runs" if tripped.any() else "0, -",
            f"{away[steady].mean():+.4f} ({steady.sum()} frames)",
            f"{1000 * np.mean(change):+.2f} over {len(change)} bursts",
        ]
        print(f"| {spec} | " + " | ".join(cells) + f" |  <!-- {time.perf_counter() - t0:.0f} s -->")

if __name__ == "__main__":
    main()
