"""export-bag refuses an output that is not a regular file in one line naming the user's path."""

from __future__ import annotations

import math
import os

import pytest
from typer.testing import CliRunner

pytest.importorskip("rosbags")

from sonarset.cli.app import app  # noqa: E402
from sonarset.format.attrs import SensorGrid  # noqa: E402


def test_export_bag_into_a_folder_or_fifo_is_refused_in_one_line(tmp_path):
    from sonarset.sim import generate

    grid = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=40, azimuth_min_rad=-math.pi / 2,
                      azimuth_max_rad=math.pi / 2, n_azimuth=18)
    generate(tmp_path / "sim.zarr", runs=1, test_runs=0, minutes=0.1, seed=4, grid=grid, workers=1)
    folder = tmp_path / "exdir.mcap"
    folder.mkdir()
    fifo = tmp_path / "pipe.mcap"
    os.mkfifo(fifo)
    for target, what in ((folder, "a folder"), (fifo, "a FIFO")):
        res = CliRunner().invoke(app, ["export-bag", str(tmp_path / "sim.zarr"), str(target)])
        assert res.exit_code == 1, res.output
        assert res.output.strip() == f"error: {target}: is {what}; the output needs an .mcap file path", res.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exdir.mcap", "pipe.mcap", "sim.zarr"]
    (tmp_path / "side.json").mkdir()  # the sidecar's place taken: nothing is written
    res = CliRunner().invoke(app, ["export-bag", str(tmp_path / "sim.zarr"), str(tmp_path / "side.mcap")])
    assert res.exit_code == 1 and res.output.strip() == (f"error: {tmp_path / 'side.json'}: is a folder; export "
                                                         "writes its sidecar there"), res.output
    assert not (tmp_path / "side.mcap").exists()
