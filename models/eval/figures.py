"""Evaluation figures: the paper's Fig. 3 per method, auto-regressive strips, metrics vs horizon,
and the "no fade" ratios against the rollout step."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import signal

from sonarset.store.atomic import save_figure
from sonarset.report.plots import draw_energyscape, pyplot

from sonarset.models.eval.result import ECHO_FLOOR, FADE_TOLERANCE, fade_summary


def correlogram(pred: np.ndarray, target: np.ndarray, max_lag: tuple[int, int] = (20, 15)) -> np.ndarray:
    """Normalised 2D cross-correlation of two images for lags up to ``max_lag`` (range, azimuth)."""
    p = (pred - pred.mean()) / (pred.std() + 1e-12)
    t = (target - target.mean()) / (target.std() + 1e-12)
    full = signal.fftconvolve(t, p[::-1, ::-1], mode="full") / p.size
    cr, ca = np.array(full.shape) // 2
    return full[cr - max_lag[0]:cr + max_lag[0] + 1, ca - max_lag[1]:ca + max_lag[1] + 1]


def write_figures(res, out: Path) -> list[str]:
    """Every figure of an evaluation result into ``out``; their paths."""
    from sonarset.store.store import open_store

    grid = open_store(res.store).grid
    paths = [prediction_figure(res, grid, out / "fig_prediction.png"),
             autoregressive_figure(res, out / "fig_autoregressive.png"),
             horizon_figure(res, out / "fig_horizon.png"),
             fade_figure(res, out / "fade.png"),
             rollout_animation(res, out / "rollout.gif")]
    return [str(p) for p in paths if p is not None]


def prediction_figure(res, grid, path: Path) -> Path:
    """Fig. 3 of the paper, one row per method: target, prediction, difference, correlogram."""
    plt = pyplot()
    ex = res.examples
    target = ex["targets"]
    methods = list(ex["methods"])
    # fixed margins: the layout solver cost as much as drawing (0.8 of 1.9 s for six methods)
    height = 3.6 * len(methods)
    fig, axes = plt.subplots(len(methods), 4, figsize=(16, height), squeeze=False,
                             gridspec_kw=dict(left=0.04, right=0.985, bottom=0.55 / height, top=1 - 0.35 / height,
                                              wspace=0.3, hspace=0.45))
    for row, m in zip(axes, methods):
        pred = ex["methods"][m][0]
        draw_energyscape(row[0], target[0], grid, "target (measured)")
        draw_energyscape(row[1], pred, grid, f"{m}: one-shot prediction")
        im = row[2].imshow(pred - target[0], origin="lower", aspect="auto", cmap="RdBu_r", vmin=-0.5, vmax=0.5)
        row[2].set_title("prediction - target")
        fig.colorbar(im, ax=row[2])
        c = correlogram(pred, target[0])
        row[3].imshow(c, origin="lower", aspect="auto", cmap="magma",
                      extent=[-(c.shape[1] // 2), c.shape[1] // 2, -(c.shape[0] // 2), c.shape[0] // 2])
        i, j = np.unravel_index(np.argmax(c), c.shape)
        row[3].plot(j - c.shape[1] // 2, i - c.shape[0] // 2, "c+", ms=12)
        row[3].set_title(f"2D correlogram (peak {c.max():.2f})")
        row[3].set_xlabel("azimuth lag [bins]")
        row[3].set_ylabel("range lag [bins]")
    save_figure(fig, path, dpi=90)
    return path


def autoregressive_figure(res, path: Path) -> Path:
    """Auto-regressive strip: measured frames, then each method's predictions and differences."""
    plt = pyplot()
    ex = res.examples
    target = ex["targets"]
    methods = list(ex["methods"])
    H = target.shape[0]
    # at most 10 columns (the paper's appendix strip); longer horizons are shown evenly spaced
    steps = sorted(set(np.linspace(0, H - 1, min(H, 10)).round().astype(int).tolist()))
    rows = 1 + 2 * len(methods)
    # a fixed grid of untitled-axis images needs no layout solver (constrained layout doubles the save time)
    fig, axes = plt.subplots(rows, len(steps), figsize=(1.6 * len(steps), 1.7 * rows), squeeze=False,
                             gridspec_kw=dict(left=0.04, right=0.995, bottom=0.01, top=0.97, wspace=0.05, hspace=0.12))
    for j, h in enumerate(steps):
        axes[0, j].imshow(target[h], origin="lower", aspect="auto", vmin=0, vmax=1)
        axes[0, j].set_title(f"t+{h + 1}", fontsize=8)
        for k, m in enumerate(methods):
            pred = ex["methods"][m][h]
            axes[1 + 2 * k, j].imshow(pred, origin="lower", aspect="auto", vmin=0, vmax=1)
            axes[2 + 2 * k, j].imshow(pred - target[h], origin="lower", aspect="auto", cmap="RdBu_r", vmin=-0.5, vmax=0.5)
    axes[0, 0].set_ylabel("measured", fontsize=8)
    for k, m in enumerate(methods):
        axes[1 + 2 * k, 0].set_ylabel(m, fontsize=8)
        axes[2 + 2 * k, 0].set_ylabel(f"{m} - meas.", fontsize=8)
    for a in axes.ravel():
        a.set_xticks([])
        a.set_yticks([])
    save_figure(fig, path, dpi=90)
    return path


def rollout_animation(res, path: Path, fps: float = 2.0) -> Path | None:
    """One rollout moving: the measured frames of the example window beside each method's
    auto-regressive predictions, one GIF frame per step of the horizon (Pillow, through matplotlib's
    canvas); None when the result holds no example."""
    from sonarset.report.plots import save_animation

    ex = res.examples
    if not ex or "targets" not in ex or not ex.get("methods"):
        return None
    plt = pyplot()
    target, methods = ex["targets"], list(ex["methods"])
    cols = 1 + len(methods)
    fig, axes = plt.subplots(1, cols, figsize=(2.2 * cols, 2.6), squeeze=False, dpi=72,
                             gridspec_kw=dict(left=0.02, right=0.98, bottom=0.02, top=0.82, wspace=0.06))
    axes = axes[0]
    shown = [axes[0].imshow(target[0], origin="lower", aspect="auto", vmin=0, vmax=1)]
    axes[0].set_title("measured", fontsize=9)
    for ax, m in zip(axes[1:], methods):
        shown.append(ax.imshow(ex["methods"][m][0], origin="lower", aspect="auto", vmin=0, vmax=1))
        ax.set_title(m, fontsize=9)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    title = fig.suptitle("", fontsize=10)

    def step(h: int) -> None:
        shown[0].set_data(target[h])
        for im, m in zip(shown[1:], methods):
            im.set_data(ex["methods"][m][h])
        title.set_text(f"window {ex.get('window', '')}: step t+{h + 1} of {target.shape[0]}")

    return save_animation(fig, step, range(target.shape[0]), path, fps)


def horizon_figure(res, path: Path) -> Path:
    """CC, NRMSD and echo F1 against the horizon, one line per method (95% intervals of the mean)."""
    plt = pyplot()
    s = res.summary()
    fig, axes = plt.subplots(1, 3, figsize=(14, 4), constrained_layout=True)
    references = {"ceiling": {"color": "0.3", "ls": "--", "label": "noise ceiling"},
                  "observable": {"color": "0.55", "ls": ":", "label": "observable ceiling"}}
    for k, ax in zip(("cc", "nrmsd", "echo_f1"), axes):
        for m in res.methods:
            # None: undefined at that horizon (constant frames); a gap in the line, not a zero
            mean = [np.nan if s[m][str(h)][k]["mean"] is None else s[m][str(h)][k]["mean"] for h in res.horizons]
            n = [s[m][str(h)][k].get("n", s[m][str(h)]["n"]) for h in res.horizons]
            sem = [np.nan if s[m][str(h)][k]["std"] is None else s[m][str(h)][k]["std"] / np.sqrt(max(1, nn))
                   for h, nn in zip(res.horizons, n)]
            style = references.get(m, {"label": m})
            ax.errorbar(res.horizons, mean, yerr=1.96 * np.array(sem), marker="o", capsize=3, **style)
        ax.set_xlabel("horizon H (frames ahead)")
        ax.set_ylabel({"echo_f1": "echo F1"}.get(k, k.upper()))
        ax.set_xticks(res.horizons)
        ax.grid(alpha=0.3)
    axes[0].legend()
    save_figure(fig, path, dpi=100)
    return path


def fade_figure(res, path: Path, fade: dict | None = None) -> Path | None:
    """The "no fade" figure: peak-pixel and echo-energy ratios (prediction / target) against the
    rollout step (a direct forecaster's: its scored horizons), one line per method, the +-15% band
    shaded. None when there is nothing to draw."""
    fade = fade_summary(res) if fade is None else fade
    if not fade:
        return None
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    for key, ax, title in (("peak_ratio", axes[0], "peak pixel"),
                           ("energy_ratio", axes[1], f"echo energy (sum of pixels > {ECHO_FLOOR:g})")):
        steps = np.arange(1, max(res.horizons) + 1)
        ax.axhspan(1 - FADE_TOLERANCE, 1 + FADE_TOLERANCE, color="0.85", zorder=0,
                   label=f"within {FADE_TOLERANCE:.0%}")
        ax.axhline(1.0, color="0.5", lw=0.8, zorder=1)
        for m, f in fade.items():
            ax.plot(f["steps"], np.asarray(f[key], float), marker="o", ms=3, label=m)
        ax.set_xlabel("rollout step (frames ahead)")
        ax.set_ylabel("prediction / target (mean over windows)")
        ax.set_title(title)
        if len(steps) <= 20:
            ax.set_xticks(steps)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("No fade: forecasts keep the targets' peak and echo energy")
    save_figure(fig, path, dpi=100)
    return Path(path)
