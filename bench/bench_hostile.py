"""The hostile-input table (issues 26, 52): slow and failing servers, absurd lengths behind a URL
and on disk, bad model cards, deep world files, signals to worker pools and during zarr's I/O,
concurrent writers, read-only stores, stores of hundreds of runs and hostile ROS bags, each against the commands a
user runs, as real processes.

    python bench/bench_hostile.py [--imports 20] [--remote-timeout 10] [--runs 400] [--flips 40] [--cases length,many-runs]

Prints one markdown row per (case, command): exit code, seconds, peak RSS, stderr lines, and the
verdict: clean when the exit code is the expected one, stderr is at most one line (validate: one
line per problem, each a finding), no traceback or "internal error", within 30 s and 2 GB. The on-disk corruption
table (60 kinds) is ``python bench/bench_readcheck.py --table``. Remote rows run with
SONARSET_REMOTE_TIMEOUT=--remote-timeout (default 10 s; the product's default is 20 s).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sonarset.testing import pool_workers, running, serve_directory  # noqa: E402

LIMIT_S, LIMIT_MB = 30.0, 2048
CLI = [sys.executable, "-m", "sonarset.cli"]
ENV = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1"}


def run(args: list, *, env: dict | None = None, timeout: float = 120, cwd=None) -> dict:
    """Run the CLI with ``args``; exit code, wall seconds, peak RSS (MB) and stderr."""
    with tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen([*CLI, *map(str, args)], stdout=subprocess.DEVNULL, stderr=err, cwd=cwd,
                                env={**ENV, **(env or {})})
        rc, peak = _wait(proc, timeout)
        seconds = time.perf_counter() - t0
        err.seek(0)
        text = err.read()
    return {"rc": rc, "s": seconds, "mb": peak / 1024, "stderr": text}


def _wait(proc: subprocess.Popen, timeout: float) -> tuple[int, int]:
    deadline = time.monotonic() + timeout
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            proc.returncode = os.waitstatus_to_exitcode(status)
            return proc.returncode, usage.ru_maxrss
        if time.monotonic() > deadline:
            proc.kill()
        time.sleep(0.05)


def lines(stderr: str) -> list[str]:
    # the multiprocessing resource tracker's note on semaphores it cleaned up is not ours to print
    return [ln for ln in stderr.splitlines() if ln.strip() and "resource_tracker" not in ln
            and "warnings.warn(" not in ln]


def verdict(result: dict, expect: int, per_problem: bool = False) -> str:
    out = lines(result["stderr"])
    problems = []
    if result["rc"] != expect:
        problems.append(f"exit {result['rc']}, expected {expect}")
    if per_problem:  # validate: one line per problem, each saying so
        if not all(ln.startswith(("invalid:", "error:")) for ln in out):
            problems.append("a line that is no finding")
    elif len(out) > 1:
        problems.append(f"{len(out)} lines")
    if "Traceback" in result["stderr"] or "internal error" in result["stderr"]:
        problems.append("traceback")
    if result["s"] > LIMIT_S:
        problems.append("too slow")
    if result["mb"] > LIMIT_MB:
        problems.append("too much memory")
    return "clean" if not problems else "**" + ", ".join(problems) + "**"


ROWS: list[str] = []


def row(case: str, command: str, result: dict, expect: int = 1) -> None:
    first = (lines(result["stderr"]) or [""])[0].replace("|", "\\|")
    if len(first) > 110:
        first = first[:107] + "..."
    ROWS.append(f"| {case} | {command} | {result['rc']} | {result['s']:.1f} | {result['mb']:.0f} | "
                f"{verdict(result, expect, command.startswith('validate'))} | {first} |")
    print(ROWS[-1], flush=True)


def reader_commands(store: str, work: Path) -> dict[str, list]:
    return {
        "info": ["info", store],
        "validate": ["validate", store],
        "validate --quick": ["validate", "--quick", store],
        "eval": ["eval", store, "--models", "naive,flow", "--samples", "20", "--no-figures", "--out", work / "e"],
        "train": ["train", store, "--preset", "tiny", "--max-steps", "1", "--out", work / "t"],
        "show": ["show", store, "--out", work / "show.png"],
    }


def remote_cases(store: Path, work: Path, timeout_s: float) -> None:
    env = {"SONARSET_REMOTE_TIMEOUT": str(timeout_s)}
    for fault in ("hang", "trickle", "server_error", "short_body"):
        with serve_directory(str(store.parent), fault) as (base, _):
            for name, args in reader_commands(f"{base}/{store.name}", work).items():
                row(f"HTTP: {fault.replace('_', ' ')}", name, run(args, env=env))
    big = work / "big.zarr"
    shutil.copytree(store, big)
    from tests.corruption_cases import _length

    import zarr

    _length(10**12)(big)
    zarr.consolidate_metadata(str(big))
    with serve_directory(str(work)) as (base, _):
        for name, args in reader_commands(f"{base}/big.zarr", work).items():
            row("HTTP: 1e12 frames declared, consolidated", name, run(args, env=env))


def card_cases(store: Path, work: Path) -> None:
    from safetensors.numpy import load_file, save_file

    pretrained = Path(__file__).resolve().parents[1] / "models" / "pretrained"
    card = json.loads((pretrained / "echopt-small.json").read_text())
    weights = load_file(pretrained / "echopt-small.safetensors")

    def edited(name: str, change=None, nan_weights: bool = False) -> Path:
        d = work / "cards" / name
        d.mkdir(parents=True)
        doc = json.loads(json.dumps(card))
        if change:
            change(doc)
        (d / "model.json").write_text(json.dumps(doc))
        w = {k: (np.full_like(v, np.nan) if nan_weights else v) for k, v in weights.items()}
        save_file(w, d / "model.safetensors")
        return d / "model.safetensors"

    cases = {
        "card: dt 0": lambda d: d["config"].update(dt=0.0),
        "card: 0 heads": lambda d: d["config"].update(n_heads=0),
        "card: 0 patch": lambda d: d["config"].update(patch=[0, 5]),
        "card: 0x0 grid": lambda d: d["config"].update(n_range=0, n_azimuth=0),
        "card: n_layers 1e6": lambda d: d["config"].update(n_layers=10**6),
        "card: unknown prior": lambda d: d["config"].update(prior="magic"),
        "card: d_embed -8": lambda d: d["config"].update(d_embed=-8),
    }
    for case, change in cases.items():
        path = edited(case.split(": ")[1].replace(" ", "_"), change)
        row(case, "eval", run(["eval", store, "--models", f"echopt:{path}", "--samples", "20", "--no-figures",
                               "--out", work / "e"]))
    path = edited("nan_weights", nan_weights=True)
    row("weights: all NaN", "eval", run(["eval", store, "--models", f"echopt:{path}", "--samples", "20",
                                         "--no-figures", "--out", work / "e"]))


def world_cases(work: Path) -> None:
    deep = work / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    row("world file: JSON nested 1e5 deep", "generate", run(["generate", work / "w.zarr", "--world", deep]))
    toml = work / "deep.toml"
    toml.write_text("a = " + "[" * 100_000 + "]" * 100_000 + "\n")
    row("world file: TOML nested 1e5 deep", "generate", run(["generate", work / "w.zarr", "--world", toml]))


def signal_cases(work: Path) -> None:
    for how, sig in (("SIGINT to the group", signal.SIGINT), ("SIGTERM", signal.SIGTERM), ("SIGKILL", signal.SIGKILL)):
        out = work / f"sig-{sig}.zarr"
        t0 = time.perf_counter()
        proc = subprocess.Popen([*CLI, "generate", out, "--minutes", "25", "--runs", "3", "--workers", "2"],
                                stderr=subprocess.PIPE, text=True, start_new_session=True, env=ENV)
        workers: set[int] = set()
        while len(workers) < 2 and time.perf_counter() - t0 < 60:
            time.sleep(0.1)
            workers = pool_workers(proc.pid)
        time.sleep(2)
        (os.killpg if sig == signal.SIGINT else os.kill)(proc.pid, sig)
        stderr = proc.communicate(timeout=60)[1]
        t1 = time.perf_counter()
        while any(map(running, workers)) and time.perf_counter() - t1 < 20:
            time.sleep(0.1)
        left = sum(map(running, workers))
        result = {"rc": proc.returncode, "s": time.perf_counter() - t1, "mb": 0,
                  "stderr": stderr + (f"\n{left} worker(s) still running" if left else "")}
        row(f"generate --workers 2, {how}", f"workers gone ({len(workers)} seen)", result,
            expect={signal.SIGINT: 130, signal.SIGTERM: 143, signal.SIGKILL: -9}[sig])


def concurrent_cases(work: Path, repeats: int) -> None:
    rng = np.random.default_rng(3)
    T, R, A = 12, 32, 16
    rec = work / "rec.npz"
    np.savez(rec, images=rng.random((T, R, A), dtype=np.float32),
             velocity=np.c_[rng.uniform(0, 0.3, T), rng.uniform(-0.5, 0.5, T)].astype(np.float32),
             time=np.arange(T) * 0.2, range=0.5 + (np.arange(R) + 0.5) * (4.5 / R),
             azimuth=-np.pi / 2 + (np.arange(A) + 0.5) * (np.pi / A))
    from sonarset import open_store
    from sonarset.store.validate import validate_store

    outcomes = {"one imported, one refused, store valid": 0}
    worst = {"rc": 1, "s": 0.0, "mb": 0.0, "stderr": ""}
    for i in range(repeats):
        store = work / f"imp{i}.zarr"
        procs = [subprocess.Popen([*CLI, "import", rec, store, "--name", "A"], stdout=subprocess.DEVNULL,
                                  stderr=subprocess.PIPE, text=True, env=ENV) for _ in range(2)]
        t0 = time.perf_counter()
        results = [(p.wait(timeout=120), p.communicate()[1]) for p in procs]
        codes = sorted(c for c, _ in results)
        ok = codes == [0, 1] and open_store(store).runs() == ["A"] and validate_store(store) == []
        key = "one imported, one refused, store valid" if ok else f"exits {codes}"
        outcomes[key] = outcomes.get(key, 0) + 1
        refusal = next((e for c, e in results if c == 1), "")
        worst = max(worst, {"rc": 1 if ok else 0, "s": time.perf_counter() - t0, "mb": 0.0, "stderr": refusal},
                    key=lambda r: r["s"])
    worst["stderr"] = f"{outcomes}\n" if len(outcomes) > 1 and outcomes[next(iter(outcomes))] < repeats else ""
    print(f"concurrent same-name imports x{repeats}: {outcomes}")
    row(f"two `import --name A` at once, x{repeats}", "import", worst, expect=1)


def read_only_cases(store: Path, work: Path) -> None:
    mnt = work / "ro"
    mnt.mkdir()
    src = work / "ro-src"
    shutil.copytree(store, src / store.name)
    mounted = subprocess.run(["mount", "--bind", src, mnt], capture_output=True).returncode == 0 and \
        subprocess.run(["mount", "-o", "remount,bind,ro", mnt], capture_output=True).returncode == 0
    if not mounted:
        print("read-only rows skipped: cannot make a read-only bind mount here (needs root)")
        return
    try:
        ro = mnt / store.name
        row("read-only store", "info", run(["info", ro]), expect=0)
        row("read-only store", "generate (nothing to do)", run(["generate", ro, *GENERATE]), expect=0)
        row("read-only store", "validate --consolidate", run(["validate", "--consolidate", ro]), expect=0)
        row("read-only store", "generate --runs 2 (other settings: refused before writing)",
            run(["generate", ro, *GENERATE_MORE]), expect=1)
    finally:
        subprocess.run(["umount", mnt])


def length_cases(store: Path, work: Path) -> None:
    """A run's length edited consistently (its ``n_frames`` and every array's shape) far beyond
    the 150 frames stored, on disk (issue 52: full validate read every declared frame)."""
    from tests.corruption_cases import _length

    for n in (10**8, 10**9):
        big = work / f"len-{n}.zarr"
        shutil.copytree(store, big)
        _length(n)(big)
        for name in ("info", "validate", "validate --quick"):
            row(f"local: {n:.0e} frames declared", name, run(reader_commands(str(big), work)[name]))


def many_runs_cases(work: Path, runs: int) -> None:
    """A store of ``runs`` runs of 20 frames on a 40 x 18 grid: its summary and checks cost per run
    (issue 52: opening a run listed every run group), and a signal during ``info``, while zarr
    opens run groups by the hundred, ends it with one line."""
    import math

    from sonarset.format.attrs import SensorGrid
    from sonarset.store.store import create_store
    from tests.conftest import make_run

    grid = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=40, azimuth_min_rad=-math.pi / 2,
                      azimuth_max_rad=math.pi / 2, n_azimuth=18)
    path = work / f"runs-{runs}.zarr"
    store = create_store(path, grid)
    for i in range(runs):
        store.write_run(f"run_{i:03d}", **make_run(20, i, grid=grid), consolidate=False)
    store.consolidate()
    case = f"{runs} runs of 20 frames"
    for name in ("info", "validate", "validate --quick"):
        row(case, name, run(reader_commands(str(path), work)[name]), expect=0)
    for how, sig in (("Ctrl-C", signal.SIGINT), ("SIGTERM", signal.SIGTERM)):
        row(f"{case}, {how} while zarr lists them", "info", interrupted(["info", path], sig),
            expect={signal.SIGINT: 130, signal.SIGTERM: 143}[sig])


def bitflip_cases(work: Path, flips: int) -> None:
    """One bit flipped at ``flips`` random offsets of an image chunk of a small store (issue 52):
    how many flips ``validate`` and the checked read catch, with checksums (format 1.2) and without
    (the same store rewritten as 1.1); then the commands on one flipped store, as real processes."""
    import math

    from sonarset.errors import SonarSetError
    from sonarset.format.attrs import SensorGrid
    from sonarset.store.store import create_store, open_store
    from sonarset.store.validate import validate_store
    from tests.conftest import make_run
    from sonarset.testing import strip_checksums

    grid = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=50, azimuth_min_rad=-math.pi / 2,
                      azimuth_max_rad=math.pi / 2, n_azimuth=30)
    rng = np.random.default_rng(52)
    for label, version in (("crc32c (1.2)", None), ("no checksum (1.1)", "1.1")):
        path = work / f"flip-{version or '1.2'}.zarr"
        store = create_store(path, grid)
        store.write_run("test_000", **make_run(24, 3, dtype="float16", grid=grid), split="test", chunk_frames=8)
        if version:
            strip_checksums(path, version)
        chunk = path / "test_000" / "images" / "c" / "1" / "0" / "0"
        intact = chunk.read_bytes()
        caught = {"validate": 0, "read": 0}
        for offset, bit in zip(rng.integers(0, len(intact), flips), rng.integers(0, 8, flips)):
            data = bytearray(intact)
            data[offset] ^= 1 << int(bit)
            chunk.write_bytes(bytes(data))
            caught["validate"] += bool([p for p in validate_store(path) if p.refused_by_readers])
            try:
                open_store(path, check=True).run("test_000").read("images")
            except SonarSetError:
                caught["read"] += 1
        chunk.write_bytes(intact)
        for how, n in caught.items():
            line = f"| bit flips in an image chunk, {label} | {how} | - | - | - | "
            if version:  # the baseline: a note, not a row to be clean
                print(f"{line}baseline | {n} of {flips} flips caught |", flush=True)
                continue
            ROWS.append(f"{line}{'clean' if n == flips else '**missed**'} | {n} of {flips} flips caught |")
            print(ROWS[-1], flush=True)
    path = work / "flip-1.2.zarr"
    chunk = path / "test_000" / "images" / "c" / "1" / "0" / "0"
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0x08
    chunk.write_bytes(bytes(data))
    commands = reader_commands(str(path), work)
    commands["show --frame 10"] = [*commands["show"], "--frame", "10"]  # a frame of the flipped chunk
    for name in ("validate", "validate --quick", "eval", "show --frame 10"):
        row("one bit flipped, crc32c (1.2)", name, run(commands[name]), expect=0 if name.endswith("quick") else 1)


def interrupted(args: list, sig: int) -> dict:
    """Run the CLI with ``args`` and send ``sig`` (to its process group for SIGINT, as a terminal
    does) 0.3 s after zarr's I/O threads came up; seconds are from the signal to the exit."""
    proc = subprocess.Popen([*CLI, *map(str, args)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, env=ENV)
    t0 = time.perf_counter()
    while _threads(proc.pid) < 4 and proc.poll() is None and time.perf_counter() - t0 < 60:
        time.sleep(0.01)
    time.sleep(0.3)
    (os.killpg if sig == signal.SIGINT else os.kill)(proc.pid, sig)
    t1 = time.perf_counter()
    try:
        stderr = proc.communicate(timeout=LIMIT_S)[1]
    except subprocess.TimeoutExpired:
        proc.kill()
        stderr = proc.communicate()[1] + "\nkilled: still running"
    return {"rc": proc.returncode, "s": time.perf_counter() - t1, "mb": 0, "stderr": stderr}


def _threads(pid: int) -> int:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0
    return int(next(line.split()[1] for line in status.splitlines() if line.startswith("Threads:")))


def bag_cases(work: Path) -> None:
    """ROS bags (issue 52): a real sensor's drive in miniature (BatSLAM2's eRTIS: 7.1 Hz, jitter,
    8 % of pings lost: one run, its gaps recorded), an import SIGKILLed and run again, a command
    clock 7 s off (estimated and warned about), ranges below zero, MCAP chunks that
    inflate to gigabytes (said or hidden), and 20,000 images of 200 x 90 uint8."""
    import math

    from sonarset.format.attrs import SensorGrid
    from tests.bag_drives import Drive, jittery_times
    from tests.test_bag_robustness import with_zero_chunk

    grid = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=200, azimuth_min_rad=-math.pi / 2,
                      azimuth_max_rad=math.pi / 2, n_azimuth=90)
    drive = Drive(times_s=jittery_times(1500, seed=1), grid=grid).write(work / "jitter.mcap")
    row("bag: 1,500 frames, 7.1 Hz, 5 % jitter, 8 % pings lost", "import-bag",
        run(["import-bag", drive, work / "jit.zarr"]), expect=0)
    row("bag: 1,500 frames, 7.1 Hz, 5 % jitter, 8 % pings lost", "validate",
        run(["validate", work / "jit.zarr"]), expect=0)
    proc = subprocess.Popen([*CLI, "import-bag", drive, work / "kill.zarr", "--name", "j"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env=ENV)
    t0 = time.monotonic()  # killed once it writes (its store built aside): a drive is one run, written fast
    while proc.poll() is None and not list(work.glob(".kill.zarr.*.tmp")) and time.monotonic() - t0 < 60:
        time.sleep(0.005)
    proc.kill()  # at once: the drive is written in about a second, and a later kill finds it done
    proc.wait()
    row("bag: import-bag SIGKILLed while it writes", "the same import again",
        run(["import-bag", drive, work / "kill.zarr", "--name", "j"]), expect=0)
    row("bag: import-bag SIGKILLed while it writes", "validate", run(["validate", work / "kill.zarr"]), expect=0)

    def below_zero(k, msg):
        msg["ranges"] = [r - 1.0 for r in msg["ranges"]]
        return msg

    small = Drive(n_frames=10)
    row("bag: ranges below zero", "import-bag", run(["import-bag", small.write(work / "neg.mcap", edit=below_zero),
                                                     work / "neg.zarr"]))
    for label, zeros, declared in (("2 GB", 2 * 10**9, None), ("5 GB", 5 * 10**9, None),
                                   ("2 GB, declaring 1 kB", 2 * 10**9, 1000)):
        bag = with_zero_chunk(small.write(work / "bomb.mcap"), zeros, declared)
        row(f"bag: a zstd chunk of {label} of zeros", "import-bag", run(["import-bag", bag, work / "bomb.zarr"]))
    from tests.test_bag_clock import moving_drive

    clock = moving_drive(1500, clock_offset_s=7.0, lost=0.0).write(work / "clock.mcap", beams_right_to_left=False)
    case = "bag: 1,500 frames, the command clock 7 s behind the sensor's"
    row(case, "import-bag (one warning, the estimate)", run(["import-bag", clock, work / "clock.zarr"]), expect=0)
    row(case, "import-bag --cmd-offset 7", run(["import-bag", clock, work / "clock7.zarr", "--cmd-offset", "7"]),
        expect=0)
    big = Drive(n_frames=20_000, grid=grid).write(work / "big.mcap")
    row("bag: 20,000 images of 200 x 90 uint8", "import-bag", run(["import-bag", big, work / "big.zarr"]), expect=0)


GENERATE = ["--minutes", "0.5", "--runs", "1", "--seed", "5"]
GENERATE_MORE = ["--minutes", "0.5", "--runs", "2", "--seed", "5"]


CASES = ("remote", "cards", "worlds", "read-only", "concurrent", "signals", "length", "many-runs", "bags", "bitflip")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--imports", type=int, default=20, help="concurrent same-name import pairs")
    ap.add_argument("--remote-timeout", type=float, default=10.0)
    ap.add_argument("--runs", type=int, default=400, help="runs in the many-runs store")
    ap.add_argument("--flips", type=int, default=40, help="bit flips in the bitflip case")
    ap.add_argument("--cases", default=",".join(CASES), help=f"the groups of rows to run, of {', '.join(CASES)}")
    args = ap.parse_args()
    cases = set(args.cases.split(","))
    if cases - set(CASES):
        ap.error(f"unknown --cases {', '.join(sorted(cases - set(CASES)))}; they are {', '.join(CASES)}")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        store = work / "s.zarr"
        subprocess.run([*CLI, "generate", store, *GENERATE], check=True, capture_output=True, env=ENV)
        print(f"{time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores, {sys.platform}")
        print("| case | command | exit | s | peak MB | verdict | what it says |")
        print("|---|---|---|---|---|---|---|")
        groups = {"remote": lambda: remote_cases(store, work, args.remote_timeout),
                  "cards": lambda: card_cases(store, work), "worlds": lambda: world_cases(work),
                  "read-only": lambda: read_only_cases(store, work),
                  "concurrent": lambda: concurrent_cases(work, args.imports), "signals": lambda: signal_cases(work),
                  "length": lambda: length_cases(store, work), "many-runs": lambda: many_runs_cases(work, args.runs),
                  "bags": lambda: bag_cases(work), "bitflip": lambda: bitflip_cases(work, args.flips)}
        for name in CASES:
            if name in cases:
                groups[name]()
        clean = sum("| clean |" in r for r in ROWS)
        print(f"\n{clean} of {len(ROWS)} rows clean")


if __name__ == "__main__":
    main()
