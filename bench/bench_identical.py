"""Do two versions of sonarset give the same outputs? (issue 15's proof that a refactor changed nothing)

    python bench/bench_identical.py --before e5410fa            # that commit against the working tree
    python bench/bench_identical.py --before HEAD~3 --after HEAD

Each side is installed from its source (a git revision, or the working tree with its uncommitted
edits) into a folder of its own and run through the same commands, in the same folder, so paths
written into outputs agree. The commands cover every engine: generate (a short simulated store),
validate, info, eval (persistence, naive, flow, EchoPT), train (a few seeded steps), the two robot
experiments (short), import and import-raw (synthetic recordings written once, shared by both
sides). Both sides use the EchoPT checkpoint shipped with ``--before``, so a retrained model does
not count as a change.

Compared byte for byte: every array chunk, every JSON document (minus the keys that record when,
how long and by which command, listed in ``VOLATILE``), every CSV, markdown and text output, and
the trained weights. Figures (PNG) are compared too; matplotlib writes no timestamps. Prints one
line per compared file that differs, a summary, and exits 1 if anything differs.
"""

from __future__ import annotations

import argparse
import hashlib
import re
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
#: JSON keys whose values are records of when, how long, where or by which command a thing ran.
VOLATILE = {"created", "created_at", "date", "started", "finished", "elapsed_s", "wall_s", "seconds", "duration_s",
            "samples_per_s", "command", "host", "hostname", "python", "platform", "torch", "time_s", "timing",
            "minutes", "train_minutes", "sonarset_version"}

#: Wall times printed in text outputs (the number is group 1).
TIMINGS = (r"\bin ([\d.]+) s\b", r"\b([\d.]+) s for \d+ windows", r"\b([\d.]+) s in all", r"\b([\d.]+) min(utes)?\b",
           r"\bin ([\d.]+) ms\b")


def install(rev: str | None, dest: Path) -> Path:
    """Install sonarset from ``rev`` (None: the working tree) into ``dest/site``; returns its source."""
    src = dest / "src"
    if rev is None:
        files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=REPO, check=True,
                               capture_output=True).stdout.decode().split("\0")
        for f in filter(None, files):
            if (REPO / f).is_file():
                (src / f).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(REPO / f, src / f)
    else:
        src.mkdir(parents=True)
        archive = subprocess.run(["git", "archive", rev], cwd=REPO, check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--target", str(dest / "site"), str(src)], check=True, capture_output=True)
    return src


def write_inputs(where: Path) -> None:
    """A synthetic external recording (images) and a raw one (microphone signals), numpy only."""
    rng = np.random.default_rng(15)
    where.mkdir(parents=True)
    T, R, A = 12, 32, 16
    rng_c = 0.5 + (np.arange(R) + 0.5) * (4.5 / R)
    az_c = -np.pi / 2 + (np.arange(A) + 0.5) * (np.pi / A)
    np.savez(where / "rec.npz", images=rng.random((T, R, A), dtype=np.float32),
             velocity=np.c_[rng.uniform(0, 0.3, T), rng.uniform(-0.5, 0.5, T)].astype(np.float32),
             time=np.arange(T) * 0.2, range=rng_c, azimuth=az_c)
    (where / "rec.json").write_text(json.dumps({"name": "ext", "split": "test"}))
    n = 2200
    signals = rng.normal(0, 0.05, (4, 32, n)).astype(np.float32)
    signals[:, :, 600:900] += np.sin(np.arange(300) * 0.9).astype(np.float32)  # one coherent echo
    np.savez(where / "raw.npz", signals=signals, velocity=np.c_[np.full(4, 0.1), np.zeros(4)].astype(np.float32),
             time=np.arange(4) * 0.2)
    (where / "raw.json").write_text(json.dumps({
        "sample_rate_hz": 200e3, "speed_of_sound_m_s": 343.0, "microphones": "ertis32", "split": "test",
        "sweep": {"f_start_hz": 25e3, "f_end_hz": 50e3, "duration_s": 0.0025, "window": "hann"},
        "grid": {"range_min": 0.5, "range_max": 1.5, "n_range": 24, "azimuth_min": -1.2, "azimuth_max": 1.2,
                 "n_azimuth": 12}}))


def commands(inputs: Path, model: Path) -> list[tuple[str, list[str]]]:
    """(name, argv after ``python -m sonarset.cli``) in order; all paths relative to the work folder."""
    m = f"echopt:{model}"
    return [
        ("generate", ["generate", "store.zarr", "--runs", "1", "--test-runs", "1", "--minutes", "0.5",
                      "--workers", "1", "--seed", "3"]),
        ("validate", ["validate", "store.zarr"]),
        ("info", ["info", "store.zarr"]),
        ("eval", ["eval", "store.zarr", "--models", f"persistence,naive,flow,{m}", "--samples", "60",
                  "--out", "eval-out", "--seed", "1"]),
        ("generate-tiny", ["generate", "tiny.zarr", "--runs", "2", "--test-runs", "1", "--minutes", "0.3",
                           "--n-range", "50", "--n-azimuth", "10", "--workers", "1", "--seed", "6"]),
        ("train", ["train", "tiny.zarr", "--preset", "tiny", "--out", "train-out", "--max-steps", "4",
                   "--batch-size", "8", "--n-val", "16", "--eval-every", "2", "--test-samples", "20",
                   "--device", "cpu", "--seed", "2", "--curriculum", "0:1,2:2", "--prior", "flow"]),
        ("eval-trained", ["eval", "tiny.zarr", "--models", "flow,echopt:train-out/model.safetensors",
                          "--samples", "30", "--out", "eval-tiny-out", "--horizons", "1,3", "--no-figures"]),
        ("control", ["experiment", "control", "--out", "control-out", "--model", str(model), "--runs", "2",
                     "--max-time", "60", "--workers", "1", "--seed", "4"]),
        ("slip", ["experiment", "slip", "--out", "slip-out", "--model", str(model), "--trials", "1",
                  "--workers", "1", "--seed", "5"]),
        ("import", ["import", str(inputs / "rec.npz"), "imported.zarr"]),
        ("import-raw", ["import-raw", str(inputs / "raw.npz"), "raw.zarr", "--workers", "1"]),
        ("info-imported", ["info", "imported.zarr"]),
    ]


def run_side(site: Path, work: Path, inputs: Path, model: Path, out: Path) -> dict[str, float]:
    """Run every command with ``site`` first on the path, in ``work``; move the results to ``out``."""
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    env = {**os.environ, "PYTHONPATH": str(site), "MPLBACKEND": "Agg", "COLUMNS": "120", "NO_COLOR": "1",
           "PYTHONHASHSEED": "0"}
    where = subprocess.run([sys.executable, "-c", "import sonarset.models; print(sonarset.models.__file__)"], env=env,
                           cwd=work, capture_output=True, text=True, check=True).stdout.strip()
    if not where.startswith(str(site)):  # an editable install must not shadow the side under test
        sys.exit(f"bench_identical: {site} is not the sonarset that runs ({where})")
    times = {}
    for name, argv in commands(inputs, model):
        t = time.perf_counter()
        res = subprocess.run([sys.executable, "-m", "sonarset.cli", *argv], cwd=work, env=env,
                             capture_output=True, text=True)
        times[name] = time.perf_counter() - t
        (work / f"{name}.stdout").write_text(f"exit {res.returncode}\n{res.stdout}\n{res.stderr}")
        if res.returncode not in (0, 1):  # validate/eval may exit 1 by design; a crash is 2+ or a traceback
            print(f"  {name}: exit {res.returncode}: {res.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
    shutil.move(str(work), str(out))
    return times


def _strip(doc):
    if isinstance(doc, dict):
        return {k: _strip(v) for k, v in doc.items() if k not in VOLATILE}
    if isinstance(doc, list):
        return [_strip(v) for v in doc]
    return doc


def _loads(text: str):
    try:
        return json.loads(text)
    except ValueError:
        return text


def digest(path: Path) -> str:
    """A file's content, with volatile JSON keys removed and timing lines of stdout dropped."""
    data = path.read_bytes()
    if path.suffix == ".safetensors":  # a JSON header (its metadata may record the command), then tensors
        n = int.from_bytes(data[:8], "little")
        header = json.loads(data[8:8 + n])
        meta = {k: _loads(v) for k, v in header.pop("__metadata__", {}).items()}
        data = json.dumps(_strip({"header": header, "meta": meta}), sort_keys=True).encode() + data[8 + n:]
    elif path.suffix in (".json", ".jsonl"):
        try:
            lines = data.decode().splitlines() if path.suffix == ".jsonl" else [data.decode()]
            data = "\n".join(json.dumps(_strip(json.loads(x)), sort_keys=True) for x in lines if x.strip()).encode()
        except ValueError:
            pass
    elif path.suffix in (".stdout", ".md", ".txt"):
        # progress bars and wall times are not outputs
        text = "\n".join(ln for ln in data.decode(errors="replace").splitlines()
                         if not any(w in ln for w in ("samples/s", "it/s", "━", "Warning")))
        for pattern in TIMINGS:
            text = re.sub(pattern, lambda m: m.group(0).replace(m.group(1), "T"), text)
        data = text.encode()
    return hashlib.sha256(data).hexdigest()


def compare(a: Path, b: Path) -> tuple[int, list[str]]:
    files_a = {p.relative_to(a) for p in a.rglob("*") if p.is_file()}
    files_b = {p.relative_to(b) for p in b.rglob("*") if p.is_file()}
    diffs = [f"only before: {p}" for p in sorted(files_a - files_b)]
    diffs += [f"only after:  {p}" for p in sorted(files_b - files_a)]
    diffs += [f"differs:     {p}" for p in sorted(files_a & files_b) if digest(a / p) != digest(b / p)]
    return len(files_a | files_b), diffs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", required=True, help="git revision of the reference code")
    ap.add_argument("--after", default=None, help="git revision to compare (default: the working tree)")
    ap.add_argument("--keep", type=Path, default=None, help="keep the outputs in this folder")
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="bench-identical-"))
    try:
        t0 = time.perf_counter()
        before_src = install(args.before, root / "before")
        install(args.after, root / "after")
        write_inputs(root / "inputs")
        model = root / "inputs" / "echopt-small.safetensors"
        for suffix in (".safetensors", ".json"):
            shutil.copy2(before_src / "models" / "pretrained" / f"echopt-small{suffix}", model.with_suffix(suffix))
        side_times = {}
        for side in ("before", "after"):
            side_times[side] = run_side(root / side / "site", root / "work", root / "inputs", model,
                                        root / side / "out")
        n, diffs = compare(root / "before" / "out", root / "after" / "out")
        print(f"# bench_identical  {args.before} vs {args.after or 'working tree'}  "
              f"{time.strftime('%Y-%m-%d %H:%M')}  {os.cpu_count()} cores  {time.perf_counter() - t0:.0f} s")
        for name in side_times["before"]:
            print(f"  {name:14s} before {side_times['before'][name]:6.1f} s   after {side_times['after'][name]:6.1f} s")
        for d in diffs:
            print(d)
        print(f"{n} files compared: " + ("all identical" if not diffs else f"{len(diffs)} differ"))
        if args.keep:
            shutil.copytree(root, args.keep, dirs_exist_ok=True)
        sys.exit(1 if diffs else 0)
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
