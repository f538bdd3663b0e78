"""Packaging: sonarset stays torch-free, and a wheel installs only the sonarset namespace."""

import graphlib
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_import_sonarset_does_not_import_torch():
    code = ("import sys, sonarset, sonarset.store.store, sonarset.windows, sonarset.store.validate, sonarset.ingest.images; "
            "assert 'torch' not in sys.modules, 'torch imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd="/")


def test_cli_help_does_not_import_torch():
    code = ("import sys; sys.argv=['sonarset','--help']\nfrom sonarset.cli.app import app\n"
            "try:\n    app()\nexcept SystemExit:\n    pass\nassert 'torch' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True, cwd="/", capture_output=True)


@pytest.mark.slow
def test_wheel_installs_in_fresh_venv(tmp_path):
    # built from a copy without the checkout's build/: setuptools never empties build/lib, so a
    # package dropped from pyproject's list would still ride along from an earlier build there
    source = tmp_path / "source"
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns("build", ".git", "*.egg-info", "__pycache__",
                                                                 ".pytest_cache", ".ruff_cache", "site"))
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation",
                    "-q", "-w", str(wheels)], check=True, cwd=tmp_path)
    (wheel,) = wheels.glob("sonarset-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert tops == {"sonarset"}, f"wheel installs top-level packages {tops}"
    assert {"sonarset/models/__init__.py", "sonarset/cli/app.py", "sonarset/sim/kernels.py",
            "sonarset/models/experiments/control.py"} <= set(names)
    # package data the simulator and the demo load at run time
    assert "sonarset/data/ertis32_microphones.csv" in names
    # every module of the checkout, each under the sonarset namespace (a package left out of
    # pyproject's list installs nowhere), and every shipped checkpoint with its card
    homes = {"sonarset": "sonarset", "models": "sonarset/models", "cli": "sonarset/cli"}
    modules = {f"{homes[top]}/{p.relative_to(ROOT / top).as_posix()}" for top in homes
               for p in (ROOT / top).rglob("*.py")}
    assert modules - set(names) == set(), "modules missing from the wheel"
    shipped = {f"sonarset/models/pretrained/{p.name}" for p in (ROOT / "models" / "pretrained").iterdir()}
    assert {"sonarset/models/pretrained/echowarp-patch4.safetensors"} <= shipped <= set(names)

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)], check=True)
    # Dependencies come from this interpreter's site-packages, appended *after* the venv's own, so
    # the sonarset that imports is the wheel's and never the checkout's.
    deps = sysconfig.get_paths()["purelib"]
    code = (f"import sys; sys.path.append({deps!r}); "
            "import sonarset, sonarset.models, sonarset.cli.app, sonarset.store.store, sonarset.sim.generation, "
            "sonarset.models.experiments.control, sonarset.models.echowarp.model; "
            f"assert sonarset.__file__.startswith({str(venv)!r}), sonarset.__file__; "
            "import importlib.util as u; "
            "assert u.find_spec('models') is None and u.find_spec('cli') is None, 'top-level models/cli'; "
            "print('ok')")
    res = subprocess.run([str(py), "-c", code], cwd=tmp_path, capture_output=True, text=True,
                         env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "ok"
    res = subprocess.run([str(venv / "bin" / "sonarset"), "--version"], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": deps})
    assert res.returncode == 0 and "sonarset" in res.stdout, res.stderr


def _sonarset_modules() -> dict[str, Path]:
    """Every module of ``sonarset/`` by its dotted name (a package by its ``__init__.py``)."""
    root, paths = ROOT / "sonarset", {}
    for p in root.rglob("*.py"):
        parts = ("sonarset", *p.relative_to(root).with_suffix("").parts)
        paths[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return paths


def _imports(module: str, path: Path, modules: set[str]) -> set[str]:
    """The modules of ``modules`` that ``module`` (its source at ``path``) imports, lazily or not,
    including imports under ``if TYPE_CHECKING:``: an annotation that names a module is a
    dependency on it all the same."""
    import ast

    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            target = ".".join(base + ([node.module] if node.module else [])) if node.level else node.module
            found |= {target} | {f"{target}.{a.name}" for a in node.names}
    return (found & modules) - {module}


def _import_graph() -> dict[str, set[str]]:
    paths = _sonarset_modules()
    return {m: _imports(m, p, set(paths)) for m, p in paths.items()}


def test_import_scan_sees_type_checking_imports(tmp_path):
    """The scan counts what only annotations need: the circle run <-> store went through them once."""
    src = tmp_path / "mod.py"
    src.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from sonarset.store.store import SonarStore\n")
    assert _imports("sonarset.x", src, {"sonarset.store.store"}) == {"sonarset.store.store"}


def test_no_import_cycle_in_sonarset():
    """No module of ``sonarset/`` imports, even lazily or for annotations only, one that imports it
    back (nor the package itself, whose ``__init__`` imports the store)."""
    graph = _import_graph()
    try:
        graphlib.TopologicalSorter(graph).prepare()
    except graphlib.CycleError as e:  # e.args[1]: the cycle, against the import direction
        pytest.fail("import cycle: " + " -> ".join(reversed(e.args[1])))


@pytest.mark.parametrize("layer", ["sonarset.format", "sonarset.store", "sonarset.sensor"])
def test_lower_layers_never_import_the_simulator_or_the_importers(layer):
    """The format, the store and the imaging chain sit below the simulator and the importers, which
    both build on them: none of their modules imports ``sonarset.sim`` or ``sonarset.ingest``."""
    graph = _import_graph()
    above = ("sonarset.sim", "sonarset.ingest")
    bad = {m: sorted(d for d in deps if d in above or d.startswith(tuple(f"{a}." for a in above)))
           for m, deps in graph.items() if m == layer or m.startswith(f"{layer}.")}
    assert not {m: d for m, d in bad.items() if d}, bad


def test_no_package_attribute_shadows_one_of_its_modules():
    """``from sonarset.sim import generate`` is the function: no module of that name hides behind it."""
    import importlib
    import types

    for package, init in _sonarset_modules().items():
        if init.name != "__init__.py" or package.startswith(("sonarset.models", "sonarset.cli")):
            continue
        pkg = importlib.import_module(package)
        for path in (p for p in init.parent.glob("*.py") if p.name != "__init__.py"):
            value = getattr(pkg, path.stem, None)
            assert value is None or isinstance(value, types.ModuleType), f"{package}.{path.stem} is shadowed by {value!r}"
