"""Every fixture in spec/fixtures behaves as manifest.json says."""

import json
from pathlib import Path

import pytest

from sonarset.store.validate import validate_store

FIX = Path(__file__).resolve().parents[1] / "spec" / "fixtures"
MANIFEST = json.loads((FIX / "manifest.json").read_text())


def test_manifest_covers_every_fixture():
    on_disk = {p.name for p in (FIX / "valid").iterdir()} | {p.name for p in (FIX / "invalid").iterdir()}
    assert on_disk == set(MANIFEST["valid"]) | set(MANIFEST["invalid"])
    assert len(MANIFEST["invalid"]) >= 12


@pytest.mark.parametrize("name", MANIFEST["valid"])
def test_valid_fixture(name):
    assert validate_store(FIX / "valid" / name) == []


@pytest.mark.parametrize("name,expected", sorted(MANIFEST["invalid"].items()))
def test_invalid_fixture(name, expected):
    problems = [str(p) for p in validate_store(FIX / "invalid" / name)]
    assert problems, f"{name} was accepted"
    assert any(expected in p for p in problems), problems
    # one corruption, one finding: messages stay specific
    assert len(problems) <= 2, problems
    assert all("\n" not in p for p in problems)


def test_generator_reproduces_the_manifest(tmp_path):
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_fixtures", FIX / "make_fixtures.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    manifest = mod.build(tmp_path)
    assert manifest == MANIFEST
    for name, expected in manifest["invalid"].items():
        assert any(expected in str(p) for p in validate_store(tmp_path / "invalid" / name)), name
