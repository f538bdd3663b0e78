"""Figures (matplotlib, Agg backend, imported lazily so the library stays light)."""

from __future__ import annotations

import os

import numpy as np

from sonarset.format.attrs import Processing, SensorGrid


def pyplot():
    """matplotlib.pyplot on the Agg backend (files only), imported on first use."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def draw_world(ax, world, trajectory: np.ndarray | None = None, marker: np.ndarray | None = None) -> None:
    for a, b in zip(world.seg_a, world.seg_b):
        ax.plot([a[0], b[0]], [a[1], b[1]], color="0.15", lw=1.5)
    for c, r in zip(world.circ_c, world.circ_r):
        ax.add_patch(pyplot().Circle(c, r, color="0.3"))
    for a, b in zip(getattr(world, "fence_a", ()), getattr(world, "fence_b", ())):  # invisible to the sonar
        ax.plot([a[0], b[0]], [a[1], b[1]], color="tab:olive", lw=0.8, ls="--")
    for box in world.spawn:
        ax.add_patch(pyplot().Rectangle((box.x[0], box.y[0]), box.x[1] - box.x[0], box.y[1] - box.y[0],
                                      fill=False, ls=":", color="tab:green"))
    if world.waypoint is not None:
        ax.plot(*world.waypoint, marker="*", color="tab:red", ms=12)
    if trajectory is not None and len(trajectory):
        ax.plot(trajectory[:, 0], trajectory[:, 1], color="tab:blue", lw=0.8, alpha=0.8)
    if marker is not None:
        x, y, th = marker
        ax.arrow(x, y, 0.4 * np.cos(th), 0.4 * np.sin(th), width=0.06, color="tab:orange", zorder=5)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def draw_energyscape(ax, image: np.ndarray, grid: SensorGrid, title: str = "") -> None:
    az = np.degrees([grid.azimuth_min_rad, grid.azimuth_max_rad])
    im = ax.imshow(image, origin="lower", aspect="auto", cmap="viridis", vmin=0, vmax=1,
                   extent=[az[0], az[1], grid.range_min_m, grid.range_max_m])
    ax.invert_xaxis()  # positive azimuth is to the robot's left: draw it on the left
    ax.set_xlabel("azimuth [deg] (left +)")
    ax.set_ylabel("range [m]")
    ax.set_title(title)
    return im


def draw_fan(ax, image: np.ndarray, grid: SensorGrid) -> None:
    """The energyscape in the sensor's own Cartesian frame: x forward (up), y left (left)."""
    r_edges = np.linspace(grid.range_min_m, grid.range_max_m, grid.n_range + 1)
    a_edges = np.linspace(grid.azimuth_min_rad, grid.azimuth_max_rad, grid.n_azimuth + 1)
    A, R = np.meshgrid(a_edges, r_edges)
    ax.pcolormesh(-R * np.sin(A), R * np.cos(A), image, cmap="viridis", vmin=0, vmax=1, shading="flat")
    ax.set_aspect("equal")
    ax.set_xlabel("right [m] (= -y)")
    ax.set_ylabel("x (forward) [m]")


def show_run(store, run_name: str, frame: int, out: str | os.PathLike, world=None) -> str:
    """Write a PNG: world map with the trajectory (if the run has poses and a world is known), the
    frame as a range x azimuth image, and as a polar fan."""
    plt = pyplot()
    run = store.run(run_name)
    if not 0 <= frame < run.n_frames:
        from sonarset.errors import SonarSetError

        raise SonarSetError(f"frame {frame} outside 0..{run.n_frames - 1} of run {run_name}")
    # checked reads: a corrupt chunk or forbidden value is refused, not drawn
    image = run.read("images", frame, frame + 1)[0].astype(np.float32)
    pose = run.read("pose") if run.has("pose") else None
    n = 3 if (world is not None or pose is not None) else 2
    fig, axes = plt.subplots(1, n, figsize=(5.2 * n, 4.8), constrained_layout=True)
    axes = list(np.atleast_1d(axes))
    if n == 3:
        ax = axes.pop(0)
        if world is not None:
            draw_world(ax, world, pose, pose[frame] if pose is not None else None)
        else:
            ax.plot(pose[:, 0], pose[:, 1], lw=0.8)
            ax.set_aspect("equal")
        ax.set_title(f"{run_name}: trajectory ({run.n_frames} frames)")
    t = float(run.read_time()[frame])
    v = run.read("velocity")[frame]  # whole: the command limits are checked on it
    im = draw_energyscape(axes[0], image, store.grid, f"frame {frame}, t = {t:.1f} s, v = {v[0]:+.2f} m/s, ω = {v[1]:+.2f} rad/s")
    draw_fan(axes[1], image, store.grid)
    axes[1].set_title("polar fan (sensor frame)")
    span = Processing.model_fields["span_db"].default
    fig.colorbar(im, ax=axes[1], label=f"energy (0 = -{span:g} dB, 1 = full scale)")
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return os.fspath(out)


def save_animation(fig, update, steps, path: str | os.PathLike, fps: float):
    """A GIF of ``fig`` drawn after ``update(step)`` for each of ``steps``, one frame each
    (Pillow through matplotlib's canvas), written atomically; the figure is closed."""
    from PIL import Image

    from sonarset.store.atomic import atomic_write

    pictures = []
    try:
        for step in steps:
            update(step)
            fig.canvas.draw()
            pictures.append(Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3]).convert(
                "P", palette=Image.Palette.ADAPTIVE))
    finally:
        pyplot().close(fig)
    return atomic_write(path, lambda p: pictures[0].save(p, format="GIF", save_all=True, append_images=pictures[1:],
                                                         duration=int(1000 / fps), loop=0))
