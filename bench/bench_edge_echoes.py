"""Where in the view does each model's one-shot forecast find the target's echoes, and where not?
    python bench/bench_edge_echoes.py --models flow,echopt:pretrained,pretrained --datasets corridor,orchard

A diagnostic of protocol v1's one-shot echo F1 (BENCHMARKS.md, "Where the one-shot echo F1 cells
stay unresolved"): on each dataset's protocol windows (the benchmark's stores, the same 1000
windows, drawn with the protocol's seed) it forecasts one step with every model (a one-horizon
pass; the protocol takes the first of a ten-horizon pass: the same network, whose bf16 kernels may
differ in the last bits) and detects the echoes of targets and forecasts as the echo metrics do
(``sonarset.scoring.echoes``). Each target echo counts as found by a model where the forecast holds
an echo within the matching tolerance, and each forecast echo as false where no target echo is
(unpaired recall and precision, as a reader of the image sees them, not the metric's one-to-one
pairing). It prints, per azimuth band (within ``--edge`` degrees of either edge of the view, and
the rest), the target echoes, each model's recall and share of false forecast echoes; the echoes
the last model misses and another finds; and at those at the edge, the brightest pixel of each
forecast within the echo term's window (``tolerance_bins``): how far below the echo level a missed
echo is drawn. "New" echoes have no echo within the tolerance in the last frame. With ``--parts``
and EchoWarp last, it also prints the terms its forecast sums (``EchoWarp.parts``) at the target
echoes' pixels, by band and by whether EchoWarp found them (the terms unclamped, from a pass of
its network apart from the rollout's), and a knock-out: the forecast, clamped to [0, 1] as the
rollout's is, with the composite warp in place of the corrected one within the edge band.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from sonarset.models.benchmark.protocol import PROTOCOL_V1
from sonarset.models.benchmark.run import method_specs
from sonarset.models.benchmark.stores import cache_dir, ensure_store
from sonarset.models.eval.evaluate import baseline_rig, window_frames
from sonarset.models.registry import make_predictor
from sonarset.scoring.echoes import EchoMatching, Peaks, echo_scores, find_echoes, tolerance_bins
from sonarset.windows import FrameBank, WindowBatcher, WindowIndex


def found(peaks: Peaks, image: np.ndarray, range_m: np.ndarray, azimuth_deg: np.ndarray, m: EchoMatching) -> np.ndarray:
    """Whether each (image, range, azimuth) point has an echo of ``peaks`` within the matching tolerance."""
    out = np.zeros(len(image), bool)
    for i in np.unique(image):
        pr, pa = peaks.of(int(i))
        if not len(pr):
            continue
        at = image == i
        d = np.maximum(np.abs(pr[None] - range_m[at, None]) / m.range_tol_m,
                       np.abs(pa[None] - azimuth_deg[at, None]) / m.azimuth_tol_deg)
        out[at] = (d <= 1).any(1)
    return out


def brightest_near(images: np.ndarray, image: np.ndarray, ri: np.ndarray, ai: np.ndarray, window) -> np.ndarray:
    """The largest pixel of each ``images[image]`` within +-``window`` bins of (ri, ai)."""
    hr, ha = window
    R, A = images.shape[1:]
    return np.array([images[i, max(0, r - hr):min(R, r + hr + 1), max(0, a - ha):min(A, a + ha + 1)].max()
                     for i, r, a in zip(image, ri, ai)])


def echowarp_parts(pred, frames: np.ndarray, commands: np.ndarray, chunk: int = 64) -> dict[str, np.ndarray]:
    """EchoWarp's one-step terms (``EchoWarp.parts``) for every window, in the predictor's precision,
    with ``outside``: whether each pixel's source in the last frame lies outside the view."""
    net = pred.predictor.model
    n_in = frames.shape[1]
    out: dict[str, list] = {}
    for lo in range(0, len(frames), chunk):
        f = torch.from_numpy(frames[lo:lo + chunk]).contiguous(memory_format=torch.channels_last)
        c = torch.from_numpy(commands[lo:lo + chunk, :n_in + 1])
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=pred.precision == "bf16"):
            parts = {k: v[:, 0].float() for k, v in net.parts(f, c, 1).items()}
            ir, ia, _ = net.sources(c, n_in, (1,))
        parts["outside"] = net.outside_view(ir, ia)[:, 0, -1].float()
        for k, v in parts.items():
            out.setdefault(k, []).append(v.numpy())
    return {k: np.concatenate(v) for k, v in out.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="flow,echopt:pretrained,pretrained")
    ap.add_argument("--datasets", default="corridor,orchard", help="protocol v1 datasets (names as in its tables)")
    ap.add_argument("--edge", type=float, default=8.0, help="degrees at each side of the view counted as its edge")
    ap.add_argument("--precision", default="auto")
    ap.add_argument("--parts", action="store_true", help="also EchoWarp's terms at the target echoes (EchoWarp last)")
    args = ap.parse_args()
    protocol, matching = PROTOCOL_V1, EchoMatching()
    specs = method_specs(args.models.split(","), protocol.reference)
    wanted = args.datasets.split(",")
    folder, stores = cache_dir(protocol), {}
    print(f"# bench_edge_echoes  {time.strftime('%Y-%m-%d')}  protocol {protocol.version}, {protocol.samples} windows, "
          f"one-shot; outer {args.edge:g} deg of azimuth on each side as the edge")
    for ds in (d for d in protocol.datasets if d.name in wanted):
        if ds.store.name not in stores:
            stores[ds.store.name] = ensure_store(ds.store, protocol, folder)[0]
        store = stores[ds.store.name]
        grid = store.grid
        bank = FrameBank.from_store(store, split="test", image_dtype=np.float32, worlds=[ds.world] if ds.world else None)
        rig, _ = baseline_rig(store, bank)
        preds = {s: make_predictor(s, grid, rig, precision=args.precision) for s in specs}
        n_in = window_frames(preds)
        index = WindowIndex.build(bank, n_in, max(protocol.horizons)).sample(protocol.samples, protocol.eval_seed)
        b = WindowBatcher.of(bank).gather(index, None, horizon=1)
        target = b.targets[:, 0]
        forecasts = {p.name: p.rollout(b.frames, b.commands[:, :n_in + 1], 1)[:, 0] for p in preds.values()}
        t = find_echoes(target, grid, matching)
        new = ~found(find_echoes(b.frames[:, -1], grid, matching), t.image, t.range_m, t.azimuth_deg, matching)
        hit = {k: found(find_echoes(v, grid, matching), t.image, t.range_m, t.azimuth_deg, matching)
               for k, v in forecasts.items()}
        lo, hi = np.degrees(grid.azimuth_min_rad), np.degrees(grid.azimuth_max_rad)

        def at_edge(azimuth_deg: np.ndarray, lo: float = lo, hi: float = hi) -> np.ndarray:
            return np.minimum(azimuth_deg - lo, hi - azimuth_deg) <= args.edge

        edge = at_edge(t.azimuth_deg)
        print(f"\n## {ds.name}: {len(index)} windows, {len(t.image)} target echoes ({new.mean():.0%} new); "
              f"edge: within {args.edge:g} deg of {lo:g} or {hi:g} deg")
        names = list(forecasts)
        print("| band | target echoes | " + " | ".join(f"{k} recall (new)" for k in names) + " | "
              + " | ".join(f"{k} forecast echoes near none" for k in names) + " |")
        print("|---" * (2 + 2 * len(names)) + "|")
        echoes = {k: find_echoes(v, grid, matching) for k, v in forecasts.items()}
        for band, sel in (("edge", edge), ("interior", ~edge)):
            cells = [(f"{hit[k][sel].mean():.3f} " + (f"({hit[k][sel & new].mean():.3f})" if (sel & new).any() else "(-)"))
                     if sel.any() else "-" for k in names]
            false = []
            for f in echoes.values():
                at = at_edge(f.azimuth_deg) == (band == "edge")
                near = found(t, f.image[at], f.range_m[at], f.azimuth_deg[at], matching)
                false.append(f"{1 - near.mean():.3f} of {at.sum()}" if at.any() else "-")
            print(f"| {band} | {sel.sum()} | " + " | ".join(cells) + " | " + " | ".join(false) + " |")
        # the echoes the last model misses and each other model finds; at those at the edge, how bright each draws them
        last = names[-1]
        r_step = (grid.range_max_m - grid.range_min_m) / grid.n_range
        a_step = np.degrees(grid.azimuth_max_rad - grid.azimuth_min_rad) / grid.n_azimuth
        ri = np.clip(((t.range_m - grid.range_min_m) / r_step).astype(int), 0, grid.n_range - 1)
        ai = np.clip(((t.azimuth_deg - np.degrees(grid.azimuth_min_rad)) / a_step).astype(int), 0, grid.n_azimuth - 1)
        window = tolerance_bins(grid, matching)
        for other in names[:-1]:
            lost = ~hit[last] & hit[other]
            gained = hit[last] & ~hit[other]
            line = (f"- {last} misses and {other} finds {lost.sum()} ({(lost & edge).sum()} at the edge, "
                    f"{(lost & new).sum()} new); the reverse {gained.sum()} ({(gained & edge).sum()} at the edge)")
            lost &= edge
            if lost.any():
                mine = brightest_near(forecasts[last], t.image[lost], ri[lost], ai[lost], window)
                theirs = brightest_near(forecasts[other], t.image[lost], ri[lost], ai[lost], window)
                dim = mine < matching.level
                line += (f"; at those at the edge {last}'s brightest pixel in the window has median {np.median(mine):.2f} "
                         f"(below the echo level {matching.level:g} at {dim.mean():.0%} of them, by a median "
                         f"{np.median(matching.level - mine[dim]) if dim.any() else 0:.2f}), {other}'s "
                         f"{np.median(theirs):.2f}; median range {np.median(t.range_m[lost]):.2f} m")
            print(line)
        net = getattr(getattr(preds[specs[-1]], "predictor", None), "model", None)
        if args.parts and callable(getattr(net, "parts", None)):
            terms = echowarp_parts(preds[specs[-1]], b.frames, b.commands)
            at = {k: v[t.image, ri, ai] for k, v in terms.items() if v.ndim == 3}
            at["shift"] = np.hypot(*terms["shift"][t.image, :, ri, ai].T) if "shift" in terms else np.zeros(len(ri))
            at["target"], at["forecast"] = target[t.image, ri, ai], forecasts[last][t.image, ri, ai]
            cols = [k for k in ("target", "composite", "warp", "older", "source", "forecast", "shift", "outside") if k in at]
            print(f"\n{last}'s terms at the target echoes' pixels (means; shift in pixels, outside: the share whose "
                  "source lies outside the view)\n\n| echoes | n | " + " | ".join(cols) + " |\n" + "|---" * (len(cols) + 2) + "|")
            for band, sel in (("edge", edge), ("interior", ~edge)):
                for state, mask in (("found", hit[last]), ("missed", ~hit[last])):
                    if (sel & mask).any():
                        print(f"| {band}, {state} | {(sel & mask).sum()} | "
                              + " | ".join(f"{at[k][sel & mask].mean():+.3f}" for k in cols) + " |")
            if "shift" in terms:  # a knock-out: the composite warp instead of the corrected one at the edge
                azimuth = np.linspace(lo, hi, grid.n_azimuth + 1)
                band_px = at_edge((azimuth[:-1] + azimuth[1:]) / 2)
                rest = terms["source"] + terms.get("older", 0)
                variants = {"as trained": np.clip(rest + terms["warp"], 0, 1),  # clamped, as the predictor's rollout
                            "knock-out": np.clip(rest + np.where(band_px, terms["composite"], terms["warp"]), 0, 1)}
                print(f"\nA knock-out: the composite warp in place of the corrected one within {args.edge:g} deg of the "
                      f"edges, from the same pass of the network (which matches the rollout's forecasts to "
                      f"{np.abs(variants['as trained'] - forecasts[last]).max():.1e})\n\n| {last} | edge recall | interior "
                      "recall | false share of the edge's forecast echoes | one-shot echo F1 (mean) |\n|---|---|---|---|---|")
                for name, v in variants.items():
                    f_v = find_echoes(v, grid, matching)
                    hit_v = found(f_v, t.image, t.range_m, t.azimuth_deg, matching)
                    at_e = at_edge(f_v.azimuth_deg)
                    false_v = 1 - found(t, f_v.image[at_e], f_v.range_m[at_e], f_v.azimuth_deg[at_e], matching).mean()
                    f1 = np.nanmean(echo_scores(v, target, grid, matching, t)["echo_f1"])
                    print(f"| {name} | {hit_v[edge].mean():.3f} | {hit_v[~edge].mean():.3f} | {false_v:.3f} of "
                          f"{at_e.sum()} | {f1:.4f} |")
        elif args.parts:
            print(f"\n--parts: the last model, {last}, has no parts (EchoWarp's)")

if __name__ == "__main__":
    main()
