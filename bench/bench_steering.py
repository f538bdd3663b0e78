"""How each predictor's forecasts steer the corridor controller, open loop, against the measured
frames they forecast (issue 51: the control experiment's midline deviation).

    python bench/bench_steering.py --worlds corridor,orchard --samples 400 --horizon 6

On protocol v1's stores (``sonarset benchmark`` caches them), windows of the test runs of each
world are forecast up to ``--horizon`` steps (6: a 1.2 s burst at 5 Hz, the control experiment's).
The controller's corridor layer (``SubsumptionController.corridor_turn``, the energy balance
of the lateral flow regions) turns each measured target and each forecast into a turn rate. It
prints, per predictor, the mean |w(forecast) - w(measured)| and its mean (a steering bias) at
steps 1, 3 and the last, over the windows where both see a lateral echo, and how often a forecast
loses a side the measurement sees or draws one it does not. This is open loop: the experiment
closes the loop, where a forecast's steering moves the robot and so the next frames.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from sonarset.models.benchmark.protocol import PROTOCOL_V1
from sonarset.models.benchmark.stores import cache_dir, ensure_store
from sonarset.models.eval.evaluate import baseline_rig
from sonarset.models.registry import make_predictor
from sonarset.sim.control import SubsumptionController
from sonarset.windows import FrameBank, WindowBatcher, WindowIndex


def turn_rate(ctrl: SubsumptionController, image: np.ndarray) -> float:
    """The corridor layer's turn rate for ``image``; NaN when neither side holds a lateral echo."""
    w = ctrl.corridor_turn(ctrl.energy(image))
    return float("nan") if w is None else w


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", default="corridor,orchard", help="world families of protocol v1's families store")
    ap.add_argument("--models", default="flow,echopt:pretrained,pretrained")
    ap.add_argument("--samples", type=int, default=400, help="windows per world (seeded)")
    ap.add_argument("--horizon", type=int, default=6, help="forecast steps (6: a 1.2 s burst at 5 Hz)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    families = next(d.store for d in PROTOCOL_V1.datasets if d.world)
    store, _ = ensure_store(families, PROTOCOL_V1, cache_dir(PROTOCOL_V1))  # simulated once, then cached
    print(f"# bench_steering  {platform.node()}  {time.strftime('%Y-%m-%d')}  horizon {args.horizon}")
    steps = sorted({0, min(2, args.horizon - 1), args.horizon - 1})
    print("| world | model | mean abs dw, steps " + "/".join(str(s + 1) for s in steps)
          + " | bias | windows seen by both (first/last) | side lost | side drawn |")
    print("|---|---|---|---|---|---|---|")
    for world in args.worlds.split(","):
        bank = FrameBank.from_store(store, split="test", image_dtype=np.float32, worlds=[world])
        rig, _ = baseline_rig(store, bank)
        ctrl = SubsumptionController(store.grid, (0.0, 0.0))
        index = WindowIndex.build(bank, 3, args.horizon).sample(args.samples, args.seed)
        batch = WindowBatcher.of(bank).gather(index)
        measured = np.array([[turn_rate(ctrl, t) for t in targets] for targets in batch.targets])
        for spec in args.models.split(","):
            predictor = make_predictor(spec, store.grid, rig)
            out = np.concatenate([predictor.rollout(batch.frames[i:i + 64], batch.commands[i:i + 64], args.horizon)
                                  for i in range(0, len(index), 64)])
            forecast = np.array([[turn_rate(ctrl, f) for f in window] for window in out])
            d = forecast - measured
            seen, lost = np.isfinite(measured), np.isfinite(measured) & ~np.isfinite(forecast)
            drawn = ~np.isfinite(measured) & np.isfinite(forecast)
            cells = [
                "/".join(f"{np.nanmean(np.abs(d[:, s])):.3f}" for s in steps),
                "/".join(f"{np.nanmean(d[:, s]):+.3f}" for s in steps),
                f"{int(np.isfinite(d[:, 0]).sum())}/{int(np.isfinite(d[:, -1]).sum())} of {int(seen[:, 0].sum())}",
                f"{int(lost[:, 0].sum())}/{int(lost[:, -1].sum())}", f"{int(drawn[:, 0].sum())}/{int(drawn[:, -1].sum())}",
            ]
            print(f"| {world} | {spec} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
