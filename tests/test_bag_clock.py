"""A command clock off from the sensor's (issue 52: BatSLAM2 fitted a 7.00 s offset by hand): the
offset estimated from the data (sonarset.ingest.bag.clock), said in the import's summary line and
warned about, with --cmd-offset as the fix."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("rosbags")
pytest.importorskip("mcap_ros2.writer")

from sonarset import open_store  # noqa: E402
from sonarset.cli.app import app  # noqa: E402
from sonarset.format.attrs import SensorGrid  # noqa: E402
from sonarset.ingest.bag.clock import estimate_offset, image_motion  # noqa: E402
from tests.bag_drives import BASE_NS, Drive, jittery_times  # noqa: E402

HZ = 7.1


def moving_drive(n_frames: int = 250, clock_offset_s: float = 7.0, seed: int = 0, lost: float = 0.08) -> Drive:
    """A drive whose images show its motion: point reflectors around a robot driven by commands
    (20 Hz, stops and turns, 12 s beyond the frames either side), imaged at 7.1 Hz with 5 % jitter
    and ``lost`` of the pings lost; the command clock runs ``clock_offset_s`` behind the sensor's (each command
    stamped that much early: ``--cmd-offset clock_offset_s`` is the fix)."""
    rng = np.random.default_rng(seed)
    grid = SensorGrid(range_min_m=0.3, range_max_m=4.0, n_range=64, azimuth_min_rad=-1.2, azimuth_max_rad=1.2,
                      n_azimuth=24)
    t = jittery_times(n_frames, hz=HZ, lost=lost, seed=seed)
    t = t - t[0]
    drive = Drive(times_s=t, grid=grid, seed=seed)
    ct = np.arange(t[0] - 12, t[-1] + 12, 0.05)
    v, w = np.zeros_like(ct), np.zeros_like(ct)
    k = 0
    while k < len(ct):  # held for 0.5 .. 2.5 s each
        m = int(rng.integers(10, 50))
        v[k:k + m], w[k:k + m] = rng.choice([0.0, 0.1, 0.2, 0.3]), rng.choice([0.0, 0.0, -0.4, 0.4])
        k += m
    fine = np.arange(ct[0], ct[-1], 0.005)  # the motion the commands caused, integrated finely
    j = np.searchsorted(ct, fine, side="right") - 1
    yaw = np.cumsum(w[j]) * 0.005
    x, y = np.cumsum(v[j] * np.cos(yaw)) * 0.005, np.cumsum(v[j] * np.sin(yaw)) * 0.005
    points = rng.uniform(-12, 12, (800, 2))
    rc, ac = grid.range_centres(), grid.azimuth_centres()
    dr, da = rc[1] - rc[0], ac[1] - ac[0]
    images = np.empty((len(t), *grid.shape), np.uint8)
    for i, ti in enumerate(t):
        q = np.searchsorted(fine, ti)
        dx, dy = points[:, 0] - x[q], points[:, 1] - y[q]
        c, s = math.cos(yaw[q]), math.sin(yaw[q])
        r, a = np.hypot(c * dx + s * dy, -s * dx + c * dy), np.arctan2(-s * dx + c * dy, c * dx + s * dy)
        seen = (r > 0.2) & (r < 4.5) & (np.abs(a) < 1.4)
        echo = np.exp(-0.5 * (((rc[:, None, None] - r[seen]) / dr) ** 2
                              + ((ac[None, :, None] - a[seen]) / (0.8 * da)) ** 2)).sum(-1)
        images[i] = np.clip((echo / 2 + rng.normal(0, 0.05, echo.shape)) * 200, 0, 255).astype(np.uint8)
    drive.images = images
    drive.command_ns = BASE_NS + np.round((ct - clock_offset_s) * 1e9).astype(np.int64)
    drive.v, drive.w = v, w
    return drive


def _estimate(drive: Drive):
    t = (drive.frame_ns - BASE_NS) * 1e-9
    return estimate_offset(t, list(drive.images), (drive.command_ns - BASE_NS) * 1e-9, drive.v, drive.w, 0.5)


@pytest.mark.parametrize("offset", [7.0, 0.0, -3.0])
def test_the_command_clock_offset_is_estimated_within_a_frame(offset):
    est = _estimate(moving_drive(clock_offset_s=offset, seed=1))
    assert est.confident and abs(est.offset_s - offset) < 1 / HZ, est


def test_images_without_motion_in_them_give_no_confident_estimate():
    drive = Drive(times_s=jittery_times(250, seed=2))  # noise images
    est = _estimate(drive)
    assert est is not None and not est.confident, est
    assert _estimate(Drive(n_frames=10)) is None  # too few frames to say


def test_image_motion_finds_the_range_and_azimuth_shift():
    frame = np.zeros((40, 12))
    frame[20, 5] = 1.0
    frame[30, 2] = 0.5
    closer = np.roll(np.roll(frame, -3, axis=0), 2, axis=1)  # echoes 3 bins closer, 2 beams over
    motion = image_motion([frame, closer])
    assert motion[0].tolist() == [0, 0, 0]
    assert abs(motion[1, 0] + 3) < 0.01 and abs(motion[1, 1] - 2) < 0.01 and motion[1, 2] > 0


def test_import_bag_warns_of_a_command_clock_7s_off_in_one_line_and_cmd_offset_fixes_it(tmp_path):
    bag = moving_drive(seed=3).write(tmp_path / "off.mcap", beams_right_to_left=False)
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr"), "--name", "off"])
    assert res.exit_code == 0, res.output
    [warning] = [ln for ln in res.output.splitlines() if ln.startswith("warning:")]
    assert "a clock offset between controller and sensor?" in warning, warning
    suggested = re.search(r"\(--cmd-offset (-?[0-9.]+) aligns them\)$", warning)
    assert suggested and abs(float(suggested[1]) - 7.0) < 1 / HZ, warning
    [summary] = [ln for ln in res.output.splitlines() if ln.startswith("imported")]
    said = re.search(r"commands vs images' motion: best at ([+-][0-9.]+) s", summary)
    assert said and abs(float(said[1]) - 7.0) < 1 / HZ, summary
    source = open_store(tmp_path / "s.zarr").run("off").attrs.source
    assert abs(source["command_offset_estimate"]["offset_s"] - 7.0) < 1 / HZ
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr"), "--name", "fixed",
                                   "--cmd-offset", "7"])
    assert res.exit_code == 0 and "warning" not in res.output, res.output
    fixed = open_store(tmp_path / "s.zarr").run("fixed").attrs.source
    assert abs(fixed["command_offset_estimate"]["offset_s"]) < 1 / HZ and fixed["command_offset_s"] == 7.0


def test_commands_that_end_before_the_frames_are_refused_naming_the_offset_that_aligns_them(tmp_path):
    drive = moving_drive(seed=4)
    t = (drive.frame_ns - BASE_NS) * 1e-9
    ct = (drive.command_ns - BASE_NS) * 1e-9 + 7.0  # on the sensor's clock
    keep = (ct > t[0] - 1) & (ct < t[-1])  # commands only while the frames were taken...
    drive.command_ns, drive.v, drive.w = drive.command_ns[keep], drive.v[keep], drive.w[keep]  # ...stamped 7 s early
    bag = drive.write(tmp_path / "d.mcap")
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr")])
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 1 and len(lines) == 1, res.output
    assert "no command over frame" in lines[0] and "the images' motion puts the commands +" in lines[0], lines[0]
    suggested = re.search(r"\(--cmd-offset ([0-9.]+) aligns them\)$", lines[0])
    assert suggested and abs(float(suggested[1]) - 7.0) < 1 / HZ, lines[0]
    res = CliRunner().invoke(app, ["import-bag", str(bag), str(tmp_path / "s.zarr"), "--cmd-offset", suggested[1]])
    assert res.exit_code == 0, res.output
