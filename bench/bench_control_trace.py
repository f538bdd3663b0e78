"""Where the control experiment's midline deviation comes from, closed loop (issue 51).

    python bench/bench_control_trace.py --models flow,echopt:pretrained,pretrained --runs 50

Runs the control experiment's bridged condition for each model (the same spawns, bursts and noise
as ``sonarset experiment control``) with a shadow controller: on every bridged frame it also
steers by the frame the sensor would have measured there without the burst. Per model it prints
the midline deviation, and by the frame's place in its burst (1 = the first frame bridged):

- the mean |w(forecast) - w(measured)|, the turn-rate error the forecast causes there;
- the mean of sign(y) (w(forecast) - w(measured)), with y the robot's lateral offset: positive
  when the forecasts steer away from the midline more than the measurements would;
- how often the forecast's turn and the measurement's differ in sign;
- over every bridged frame, the mean "away" with its standard error over the runs (a steering
  bias: the turn rates themselves are small, a few 0.01 rad/s, and the measured frame's own noise
  makes single frames' differences noisy), and on the bridged frames more than 2 cm off the
  midline alone, with how many there are.

Then the deviation itself: the mean |y| on bridged frames against the others, and its mean change
over a burst (|y| at the frame after the burst minus at its first frame).
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="flow,echopt:pretrained,pretrained")
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0, help="the control experiment's default")
    ap.add_argument("--workers", type=int, default=None)
    args = ap.parse_args()
    grid, seeds = SensorGrid.default(), spawn_seeds(args.seed, args.runs)
    print(f"# bench_control_trace  {platform.node()}  {time.strftime('%Y-%m-%d')}  {args.runs} runs")
    print("| model | midline dev. [mm] | mean abs dw at frame 1/3/6 [rad/s] | away from midline 1/3/6 "
          "| sign differs 1/3/6 | away, all bridged frames [rad/s] | away, 2 cm or more off [rad/s] | abs y bridged / not [mm] "
          "| abs y change over a burst [mm] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for spec in args.models.split(","):
        t0 = time.perf_counter()
        eps = parallel_map(run_episode, [Episode(i, s, f"bursts+{spec}", grid, shadow=True)
                                         for i, s in enumerate(seeds)], args.workers)
        place, dw, away, y_bridged, y_other, change, run_away = [], [], [], [], [], [], []
        off = []  # per bridged frame: is the robot 2 cm or more off the midline
        for ep in eps:
            bridged = ep["predicted"]
            y = ep["pose"][:len(bridged), 1]
            at = burst_places(bridged)
            d = ep["w"] - ep["w_measured"]
            place.append(at[bridged]), dw.append(d[bridged]), away.append((np.sign(y) * d)[bridged])
            if bridged.any():
                run_away.append(away[-1].mean())
            y_bridged.append(np.abs(y[bridged])), y_other.append(np.abs(y[~bridged]))
            off.append(np.abs(y[bridged]) >= 0.02)
            starts = np.flatnonzero(at == 1)
            ends = np.flatnonzero(bridged[:-1] & ~bridged[1:]) + 1  # the first frame after each burst
            change += [abs(y[e]) - abs(y[s]) for s, e in zip(starts, ends)]
        place, dw, away, off = (np.concatenate(a) for a in (place, dw, away, off))
        sign_differs = []
        for ep in eps:
            b = ep["predicted"]
            sign_differs.append(np.sign(ep["w"][b]) != np.sign(ep["w_measured"][b]))
        sign_differs = np.concatenate(sign_differs)
        ks = [k for k in (1, 3, 6) if (place == k).any()]
        cells = [
            f"{1000 * np.nanmean([e['midline_deviation_m'] for e in eps]):.2f}",
            "/".join(f"{np.abs(dw[place == k]).mean():.3f}" for k in ks),
            "/".join(f"{away[place == k].mean():+.3f}" for k in ks),
            "/".join(f"{sign_differs[place == k].mean():.0%}" for k in ks),
            f"{np.mean(run_away):+.4f} +- {np.std(run_away, ddof=1) / np.sqrt(len(run_away)):.4f}",
            f"{away[off].mean():+.4f} ({off.sum()} frames)",
            f"{1000 * np.concatenate(y_bridged).mean():.2f} / {1000 * np.concatenate(y_other).mean():.2f}",
            f"{1000 * np.mean(change):+.2f} over {len(change)} bursts",
        ]
        print(f"| {spec} | " + " | ".join(cells) + f" |  <!-- {time.perf_counter() - t0:.0f} s -->")


if __name__ == "__main__":
    main()
