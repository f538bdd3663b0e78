from pathlib import Path

import pytest
from pydantic import ValidationError

from sonarset.format.attrs import SensorGrid, StoreAttrs, parse_version
from sonarset.format.schemas import SCHEMAS, json_schema_text
from sonarset.format.sidecars import RecordingMeta

SCHEMA_DIR = Path(__file__).resolve().parents[1] / "spec" / "schema"


@pytest.mark.parametrize("kind", sorted(SCHEMAS))
def test_committed_json_schema_is_current(kind):
    committed = (SCHEMA_DIR / f"{kind}.schema.json").read_text()
    assert committed == json_schema_text(kind), (
        f"spec/schema/{kind}.schema.json is stale: run `sonarset schema {kind} > spec/schema/{kind}.schema.json`")


def test_default_grid_matches_design():
    g = SensorGrid.default()
    az = g.azimuth_centres()
    assert g.shape == (200, 90)
    assert az[0] == pytest.approx(-89 * 3.141592653589793 / 180) and az[-1] == pytest.approx(89 * 3.141592653589793 / 180)
    assert g.range_centres()[0] == pytest.approx(0.5 + 4.5 / 400)


def test_grid_from_centres_round_trip_and_rejects_nonuniform():
    g = SensorGrid.default()
    assert SensorGrid.from_centres(g.range_centres(), g.azimuth_centres()).matches(g)
    r = g.range_centres().copy()
    r[5] += 0.01
    with pytest.raises(ValueError, match="not uniformly spaced"):
        SensorGrid.from_centres(r, g.azimuth_centres())


def test_version_parsing():
    assert parse_version("1.0") == (1, 0) and parse_version("12.3") == (12, 3)
    for bad in ("1", "v1.0", 1.0, None, "1.0.0"):
        with pytest.raises(ValueError):
            parse_version(bad)


def test_store_attrs_accept_unknown_keys_from_later_minor():
    a = StoreAttrs.model_validate({"format_version": "1.4", "grid": SensorGrid.default().model_dump(), "new": 1})
    assert a.format_version == "1.4"
    assert a.model_dump()["new"] == 1  # kept, so a rewrite of the attributes does not drop it


def test_recording_meta_rejects_unknown_units():
    with pytest.raises(ValidationError):
        RecordingMeta.model_validate({"units": {"range": "inch"}})
    with pytest.raises(ValidationError):
        RecordingMeta.model_validate({"colour": "red"})
