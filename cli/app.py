"""The ``sonarset`` command line: a thin layer over the library API.

User errors (bad files, bad stores, bad arguments) end with one line on stderr and a non-zero
exit, never a traceback. Set SONARSET_DEBUG=1 to see the traceback of an unexpected error.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from sonarset import __version__

from sonarset.cli.choices import (Beamformer, Device, Optimizer, Precision, Preset, Prior, ProcessingProfile, Psf, Schedule,
                      SchemaKind, value)
from sonarset.cli.common import err, fail, out, per_name_progress, progress_bar, user_errors
from sonarset.cli.experiment import experiment_app
from sonarset.cli.options import MetaPath, Model, ModelDevice, ModelPrecision, OutStore, Overwrite, RunName, RunSplit

app = typer.Typer(
    name="sonarset",
    help="In-air sonar prediction: SonarSet stores, simulator, EchoPT and baselines.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.add_typer(experiment_app, name="experiment")
def _version(value: bool) -> None:
    if value:
        out.print(f"sonarset {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    pass


@app.command()
@user_errors
def info(
    store: str = typer.Argument(..., help="Store path or fsspec URL."),
    as_json: bool = typer.Option(False, "--json", help="Print machine-readable JSON."),
) -> None:
    """Summarise a store: format version, grid, runs, frames and size."""
    from sonarset.report.overview import describe_sensing, human_bytes, store_summary
    from sonarset.store.store import open_store

    s = open_store(store, check=True)
    summary = store_summary(s)
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    out.print(f"[bold]{s.location}[/]  SonarSet {s.format_version}  ({s.attrs.created_by or 'unknown writer'})")
    for line in describe_sensing(s):
        out.print(line, highlight=False)
    table = Table("run", "split", "world", "frames", "duration", "images", "optional")
    for r in summary["runs"]:
        table.add_row(r["name"], r["split"], r["world"] or "-", str(r["frames"]), f"{r['duration_s']:.1f} s",
                      r["image_dtype"], ", ".join(r["optional"]) or "-")
    out.print(table)
    out.print(f"{len(summary['runs'])} complete run(s), {summary['frames']} frames, {human_bytes(summary['bytes'])} on disk")
    incomplete = summary["incomplete_runs"]
    if incomplete:
        out.print(f"[yellow]{len(incomplete)} incomplete run(s) ignored: {', '.join(incomplete)}[/]")


@app.command()
@user_errors
def validate(
    store: str = typer.Argument(..., help="Store path or fsspec URL."),
    quick: bool = typer.Option(False, "--quick", help="Check metadata only; do not read the data chunks."),
    consolidate: bool = typer.Option(False, "--consolidate",
                                     help="Rewrite stale consolidated metadata, then validate."),
    allow_implausible: bool = typer.Option(False, "--allow-implausible",
                                           help="Report implausible values (unit mistakes?) as warnings, not errors."),
) -> None:
    """Check a store against the SonarSet spec: exit 0 if valid, 1 with one line per problem."""
    from sonarset.store.validate import validate_store

    if consolidate:
        from sonarset.store.store import open_store

        open_store(store, "r+").consolidate()
    with progress_bar() as bar:
        task = bar.add_task("validating", total=None)

        def progress(where: str, done: int, total: int) -> None:
            bar.update(task, description=where.rsplit("/", 2)[-2], completed=done, total=total)

        problems = validate_store(store, check_data=not quick, progress=progress)
    from sonarset.format.plausibility import Implausible

    allowed = [p for p in problems if allow_implausible and isinstance(p, Implausible)]
    problems = [p for p in problems if not (allow_implausible and isinstance(p, Implausible))]
    for p in allowed:
        err.print(f"[yellow]warning:[/] {p}", highlight=False, soft_wrap=True)
    if problems:
        for p in problems:
            label = "implausible" if isinstance(p, Implausible) else "invalid"
            err.print(f"[bold red]{label}:[/] {p}", highlight=False, soft_wrap=True)
        if any(isinstance(p, Implausible) for p in problems):
            err.print("note: if the implausible values are right, pass --allow-implausible", highlight=False)
        raise typer.Exit(1)
    out.print(f"{store}: valid SonarSet store" + (f" ({len(allowed)} implausible value(s) allowed)" if allowed else ""))


@app.command("import")
@user_errors
def import_(
    src: Annotated[Path, typer.Argument(help="A .npz file, or a directory of .npy files with recording.json.")],
    out_store: OutStore, meta: MetaPath = None, name: RunName = None, split: RunSplit = None, overwrite: Overwrite = False,
    allow_implausible: bool = typer.Option(False, "--allow-implausible",
                                           help="Import values the plausibility checks question (unit mistakes?); "
                                                "each is printed as a warning."),
) -> None:
    """Validate an external recording completely, then write it as one run of a store."""
    from sonarset.ingest.images import import_recording

    def warn(line: str) -> None:
        err.print(f"[yellow]warning:[/] {line}", highlight=False, soft_wrap=True)

    run = import_recording(src, out_store, meta_path=meta, name=name, split=split, overwrite=overwrite,
                           allow_implausible=allow_implausible, warn=warn)
    out.print(f"imported {src} -> {out_store}/{run.name} ({run.n_frames} frames, split {run.split})")


@app.command("import-raw")
@user_errors
def import_raw_(
    src: Annotated[Path, typer.Argument(help="Microphone signals: a .npz, or a directory of .npy files with "
                                             "recording.json.")],
    out_store: OutStore, meta: MetaPath = None, name: RunName = None, split: RunSplit = None, overwrite: Overwrite = False,
    processing: ProcessingProfile = typer.Option("ertis", "--processing", help="Energyscape profile."),
    beamformer: Optional[Beamformer] = typer.Option(None, "--beamformer", help="Default: the profile's."),
    workers: int = typer.Option(2, "--workers", min=1, help="Threads beamforming measurements."),
) -> None:
    """Beamform raw microphone recordings into energyscapes, validated completely, as one run of a store."""
    from sonarset.ingest.raw import import_raw

    with progress_bar() as bar:
        task = bar.add_task("beamforming", total=None)
        run = import_raw(src, out_store, meta_path=meta, name=name, split=split, processing=processing.value,
                         beamformer=value(beamformer), overwrite=overwrite, workers=workers,
                         progress=lambda done, total: bar.update(task, completed=done, total=total))
    out.print(f"imported {src} -> {out_store}/{run.name} ({run.n_frames} frames, split {run.split}, "
              f"{run.store.processing.describe()})", highlight=False)


@app.command()
@user_errors
def schema(
    kind: SchemaKind = typer.Argument("store", help="The document."),
) -> None:
    """Print the JSON Schema of a SonarSet document (root, run or import-sidecar attributes)."""
    from sonarset.format.attrs import json_schema_text

    sys.stdout.write(json_schema_text(kind.value))


@app.command()
@user_errors
def generate(
    out_store: str = typer.Argument(..., metavar="OUT", help="Store to write (created, or resumed)."),
    runs: Optional[int] = typer.Option(None, "--runs", min=0, help="Training runs of a single --world (default 10)."),
    minutes: float = typer.Option(25.0, "--minutes", min=0.0, help="Length of each run (5 Hz frames)."),
    test_runs: int = typer.Option(1, "--test-runs", min=0,
                                  help="Test runs (split 'test') of each world, never for training."),
    workers: Optional[int] = typer.Option(None, "--workers", min=1, help="Parallel processes (default: all cores)."),
    seed: int = typer.Option(0, "--seed", help="Master seed; same seed, same arrays, whatever the workers."),
    world: str = typer.Option("lab", "--world",
                              help="A world family (lab, corridor, orchard, warehouse, rooms; each run its own "
                                   "variant) or a JSON/TOML world file; or a mix with each world's training runs: "
                                   "lab:4,orchard:2,warehouse:2,rooms:2 (then no --runs)."),
    snr_db: float = typer.Option(5.0, "--snr-db", help="SNR at the microphones, dB."),
    psf: Psf = typer.Option("array", "--psf", help="Azimuth PSF: array (eRTIS delay-and-sum, with side lobes) or "
                                                  "mainlobe."),
    processing: ProcessingProfile = typer.Option("ertis", "--processing",
                                                 help="Images: ertis (DMAS3 + coherence factor, energyscape "
                                                      "post-processing, the sensor toolchain's) or raw (delay-and-sum "
                                                      "energy, format 1.0's)."),
    n_range: int = typer.Option(200, "--n-range", min=2, help="Range bins over 0.5-5 m."),
    n_azimuth: int = typer.Option(90, "--n-azimuth", min=2, help="Azimuth bins over -90..+90 deg."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler",
                                            help="Dask scheduler address (tcp://host:8786), or 'local' for a "
                                                 "LocalCluster of --workers processes; default: local processes."),
) -> None:
    """Simulate runs into a SonarSet store (a path or an fsspec URL); re-run the same command to resume."""
    import time

    from rich.progress import MofNCompleteColumn, TimeElapsedColumn

    from sonarset.format.attrs import SensorGrid
    from sonarset.sim import generate as gen
    from sonarset.sim.runs import world_mix

    grid = SensorGrid(range_min_m=0.5, range_max_m=5.0, n_range=n_range,
                      azimuth_min_rad=-math.pi / 2, azimuth_max_rad=math.pi / 2, n_azimuth=n_azimuth)
    t0 = time.perf_counter()
    columns = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), TimeRemainingColumn()]
    with Progress(*columns, console=err, disable=not err.is_terminal) as bar:
        tasks: dict[str, int] = {}
        started: dict[str, float] = {}

        def progress(name: str, done: int, total: int) -> None:
            if name not in tasks:
                tasks[name] = bar.add_task(name, total=total, rate="")
                started[name] = time.perf_counter()
            rate = done / max(time.perf_counter() - started[name], 1e-9)
            bar.update(tasks[name], completed=done, rate=f"{rate:,.0f} frames/s")

        written = gen(out_store, runs=runs, test_runs=test_runs, minutes=minutes, seed=seed, world=world,
                      snr_db=snr_db, psf=psf.value, processing=processing.value, workers=workers, grid=grid,
                      progress=progress, scheduler=scheduler)
    dt = time.perf_counter() - t0
    planned = sum(n + test_runs for _, n in world_mix(world, runs))
    out.print(f"{out_store}: wrote {len(written)} run(s) in {dt:.1f} s"
              + (f" ({planned - len(written)} already complete)" if len(written) < planned else ""))


@app.command()
@user_errors
def show(
    store: str = typer.Argument(..., help="Store path or fsspec URL."),
    run: Optional[str] = typer.Option(None, "--run", help="Run name (default: the first)."),
    frame: int = typer.Option(0, "--frame", min=0, help="Frame index."),
    out_png: Path = typer.Option(Path("sonarset-show.png"), "--out", help="PNG to write."),
) -> None:
    """Plot the world and trajectory of a run and one energyscape (image and polar fan)."""
    from sonarset.report.overview import show as show_store
    from sonarset.store.store import open_store

    out.print(f"wrote {show_store(open_store(store, check=True), run, frame, out_png)}")


def _int_list(text: str, what: str) -> list[int]:
    try:
        values = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        fail(f"{what} must be comma-separated integers, got {text!r}", 2)
    if not values or min(values) < 1:
        fail(f"{what} must be positive integers, got {text!r}", 2)
    return values


@app.command("eval")
@user_errors
def eval_(
    store: str = typer.Argument(..., help="Store path or fsspec URL."),
    models: str = typer.Option("persistence,naive,flow", "--models",
                               help="Comma-separated: persistence, naive, flow, echopt:PATH (or echopt:pretrained)."),
    horizons: str = typer.Option("1,3,5,10", "--horizons", help="Prediction horizons (1 = one-shot)."),
    samples: int = typer.Option(1000, "--samples", min=1, help="Windows drawn (seeded), shared by all methods."),
    out_dir: Path = typer.Option(Path("eval-out"), "--out", help="Directory for metrics.json, per_window.csv, report.md, figures."),
    split: str = typer.Option("test", "--split", help="Split to evaluate on."),
    worlds: str = typer.Option("", "--worlds", help="Only runs of these world families, comma-separated "
                                                     "(default: every run of the split)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the window draw and the bootstrap."),
    device: ModelDevice = Device("cpu"),
    precision: ModelPrecision = Precision("auto"),
    figures: bool = typer.Option(True, "--figures/--no-figures", help="Write the PNG figures."),
    ceiling: bool = typer.Option(False, "--ceiling",
                                 help="Add the noise ceiling (target frames of simulated runs re-rendered with "
                                      "independent noise: how much of a frame is predictable at all) and the "
                                      "observable ceiling (re-rendered from only the reflectors the window's context "
                                      "heard: how much the context could know)."),
) -> None:
    """Evaluate predictors on the same windows: the paper's table, statistics and figures."""
    from sonarset.store.store import open_store
    from sonarset.models.eval.report import results_table, write_report
    from sonarset.models.eval.evaluate import evaluate

    specs = [m.strip() for m in models.split(",") if m.strip()]
    s = open_store(store, check=True)
    with progress_bar() as bar:
        progress = per_name_progress(bar)
        res = evaluate(s, specs, horizons=tuple(_int_list(horizons, "--horizons")), samples=samples,
                       split=split, seed=seed, device=device.value, precision=precision.value, progress=progress,
                       ceiling=ceiling, worlds=[w.strip() for w in worlds.split(",") if w.strip()] or None)
    write_report(res, out_dir, figures=figures)
    _print_notes(res.notes)
    out.print(results_table(res, with_paper=False))
    out.print(f"{len(res.window_ids)} windows of split {split!r}; report: {out_dir / 'report.md'}")


def _mean(entry: dict) -> str:
    return "undefined" if entry["mean"] is None else f"{entry['mean']:.3f}"


def _print_notes(notes: list[str]) -> None:
    for note in notes:
        out.print(note, style="yellow", markup=False, highlight=False)


@contextlib.contextmanager
def _training_bar(show: bool):
    """The progress callback of a training run: loss, validation and speed on a terminal, a line
    per validation otherwise."""
    from rich.progress import MofNCompleteColumn, TimeElapsedColumn

    columns = [TextColumn("[bold]training"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[info]}"),
               TimeElapsedColumn(), TimeRemainingColumn()]
    with Progress(*columns, console=err, disable=not (err.is_terminal and show)) as bar:
        task = bar.add_task("train", total=None, info="")

        def progress(rec: dict) -> None:
            info = f"loss {rec['train_loss']:.5f}"
            if "val_loss" in rec:
                info += f" val {rec['val_loss']:.5f} (best {rec['best_val_loss']:.5f}) {rec['samples_per_s']:.0f} samples/s"
                if not err.is_terminal:
                    err.print(f"step {rec['step']}/{rec['total_steps']} epoch {rec['epoch']:.2f} {info}", highlight=False)
            bar.update(task, completed=rec["step"], total=rec["total_steps"], info=info)

        yield progress


@app.command()
@user_errors
def train(
    store: str = typer.Argument(..., help="Training store (its 'train' split; 'test' is never used for training)."),
    preset: Preset = typer.Option("small", "--preset", help="small (trains on a CPU), paper (~9 M parameters), tiny (tests)."),
    out_dir: Path = typer.Option(..., "--out", help="Run directory: model.safetensors + model.json, metrics.jsonl, state.safetensors"),
    epochs: int = typer.Option(1000, "--epochs", min=1, help="Passes over the training windows (paper: 1000)."),
    batch_size: int = typer.Option(64, "--batch-size", min=1),
    lr: float = typer.Option(5e-5, "--lr", help="Adam learning rate (paper: 5e-5)."),
    weight_decay: float = typer.Option(1e-4, "--weight-decay", help="L2 regularisation (paper: 1e-4)."),
    optimizer: Optimizer = typer.Option("adam", "--optimizer", help="adam (paper: L2 in the gradient) or adamw "
                                                                    "(decoupled decay; use it with a prior)."),
    schedule: Schedule = typer.Option("none", "--schedule", help="none (paper) or cosine."),
    seed: int = typer.Option(0, "--seed"),
    device: Device = typer.Option("auto", "--device"),
    precision: ModelPrecision = Precision("auto"),
    resume: bool = typer.Option(False, "--resume", help="Continue a killed run exactly where it stopped."),
    eval_every: int = typer.Option(0, "--eval-every", min=0, help="Steps between validations/checkpoints (0: each epoch)."),
    max_steps: int = typer.Option(0, "--max-steps", min=0, help="Stop after this many steps (0: no limit)."),
    max_minutes: float = typer.Option(0.0, "--max-minutes", min=0.0, help="Stop after this wall time (0: no limit)."),
    compile_: bool = typer.Option(False, "--compile", help="torch.compile the model (GPU)."),
    test_samples: int = typer.Option(1000, "--test-samples", min=0, help="Test windows for the card's metrics (0: skip)."),
    n_val: int = typer.Option(1600, "--n-val", min=1, help="Random validation windows (paper: 1600)."),
    prior: Optional[Prior] = typer.Option(None, "--prior", help="What the model corrects: none (paper), last (frame) "
                                                                 "or flow (its acoustic-flow warp). Default: the "
                                                                 "preset's (paper none, small flow)."),
    loss: str = typer.Option("mse", "--loss", help="mse, l1, gdl (image-gradient difference), cc (1 - CC), "
                                                   "w1 (1-D Wasserstein of the pixel values), energy (the "
                                                   "batch's echo-energy deficit), or a weighted sum: "
                                                   "cc=1,w1=50."),
    curriculum: str = typer.Option("1", "--curriculum", help="Rollout steps k of the unrolled loss: k, or "
                                                             "step:k,... (e.g. 0:1,300:2,600:4,900:6)."),
    pushforward: bool = typer.Option(False, "--pushforward", help="Only the last rollout step carries gradient."),
    context_noise: float = typer.Option(0.0, "--context-noise", min=0.0, help="Std of Gaussian noise on the context frames."),
    val_horizon: int = typer.Option(0, "--val-horizon", min=0, help="Rollout steps of the validation loss "
                                                                     "(0: the curriculum's longest)."),
    init: str = typer.Option("", "--init", help="Fine-tune: start from this checkpoint's weights (pretrained or a "
                                                 "path; same preset, prior, grid and images); the optimizer starts fresh."),
    worlds: str = typer.Option("", "--worlds", help="Train only on runs of these world families, comma-separated "
                                                     "(e.g. lab,orchard; default: every training run)."),
    n_in: int = typer.Option(0, "--n-in", min=0, help="Input frames per window (0: the preset's, the paper's 3)."),
) -> None:
    """Train EchoPT; the best validation weights are kept as OUT/model.safetensors with a model card.

    Killed at any point, the same command with --resume continues exactly (OUT/state.safetensors)."""
    from sonarset.models.echopt.train import TrainConfig, add_test_metrics
    from sonarset.models.echopt.train import train as run_training
    from sonarset.store.store import open_store

    s = open_store(store, check=True)
    cfg = TrainConfig(preset=preset.value, epochs=epochs, batch_size=batch_size, lr=lr, weight_decay=weight_decay,
                      schedule=schedule.value, seed=seed, device=device.value, eval_every=eval_every,
                      max_steps=max_steps, max_minutes=max_minutes, compile=compile_, test_samples=test_samples,
                      n_val=n_val, prior=value(prior) or "", loss=loss, curriculum=curriculum, pushforward=pushforward,
                      optimizer=optimizer.value, context_noise=context_noise, val_horizon=val_horizon, init=init,
                      precision=precision.value, worlds=worlds, n_in=n_in)
    main = int(os.environ.get("RANK", "0")) == 0  # under torchrun only rank 0 reports
    with _training_bar(main) as progress:
        res = run_training(s, out_dir, cfg, resume=resume, progress=progress)
    if not main:
        return
    out.print(f"{res.steps} steps ({res.epochs_done:.2f} epochs); best validation loss {res.best_val_loss:.6f}; "
              f"weights: {out_dir / 'model.safetensors'}")
    if test_samples and s.runs("test"):
        test = add_test_metrics(out_dir, s, samples=test_samples, device=cfg.device, precision=cfg.precision)
        r = test["results"]
        for m in ("flow", "echopt"):
            one = r[m]["1"]
            out.print(f"test one-shot {m}: CC {_mean(one['cc'])}, NRMSD {_mean(one['nrmsd'])}")


@app.command()
@user_errors
def demo(
    out_dir: Path = typer.Option(Path("demo-out"), "--out", help="Directory for the store, report and figures."),
    minutes: float = typer.Option(25.0, "--minutes", min=0.5, help="Length of the fresh test run."),
    samples: int = typer.Option(1000, "--samples", min=10, help="Test windows."),
    seed: int = typer.Option(2026, "--seed", help="Seed of the fresh run (the shipped model was trained on seed 0)."),
    model: Model = "pretrained",
    device: ModelDevice = Device("auto"),
    precision: ModelPrecision = Precision("auto"),
) -> None:
    """Simulate a fresh test run and compare the pretrained EchoPT with persistence, naive and flow
    (and the noise and observable ceilings)."""
    import time

    from sonarset.models import demo as pipeline
    from sonarset.models.eval.report import results_table, write_report

    pipeline.check_model(model)  # a bad model fails now, not after the simulation
    t0 = time.perf_counter()
    store_path = out_dir / "test.zarr"
    out.print(f"simulating a fresh {minutes:g}-minute test run (seed {seed}) -> {store_path}")
    with progress_bar() as bar:
        task = bar.add_task("simulating", total=None)
        s = pipeline.simulate_fresh_run(store_path, minutes=minutes, seed=seed,
                                        progress=lambda name, done, total: bar.update(task, completed=done, total=total))
    out.print(pipeline.images_note(model, s), highlight=False)
    out.print(pipeline.runs_in(model, precision.value, device.value), highlight=False)
    out.print(f"evaluating persistence, naive, flow and EchoPT ({model}) on {samples} windows, horizons 1, 3, 5, 10, "
              "with the noise and observable ceilings")
    with progress_bar() as bar:
        res = pipeline.evaluate_fresh_run(s, model, samples=samples, device=device.value, precision=precision.value,
                                          progress=per_name_progress(bar))
    write_report(res, out_dir)
    _print_notes(res.notes)
    out.print(results_table(res, with_paper=True))
    for line in pipeline.echopt_against_flow(res):
        out.print(line)
    out.print(f"report: {out_dir / 'report.md'} (figures beside it); {time.perf_counter() - t0:.0f} s in all")


@app.command("export-onnx")
@user_errors
def export_onnx_(
    model: str = typer.Argument(..., metavar="MODEL", help="EchoPT checkpoint: pretrained, a run directory or a "
                                                          ".safetensors path."),
    out_path: Path = typer.Argument(..., metavar="OUT.onnx", help="The ONNX file to write."),
) -> None:
    """Export EchoPT to ONNX for onnxruntime: a dynamic batch axis, the flow prior inside the graph,
    the model card in the metadata; checked against torch before it is written."""
    from sonarset.models.echopt.onnx_export import export_onnx

    e = export_onnx(model, out_path)
    out.print(f"wrote {e.path} ({e.bytes / 1e6:.1f} MB)", highlight=False)
    if e.max_abs_diff is None:
        out.print("note: onnxruntime is not installed, so the export was not run; pip install 'sonarset[onnx]'",
                  style="yellow", highlight=False)
    else:
        out.print(f"onnxruntime matches torch to {e.max_abs_diff:.1e} (max abs) on {e.check_windows} random windows",
                  highlight=False)
    out.print(f"use it as --models echopt:{e.path} (eval) or --model {e.path} (demo, experiments)", highlight=False)


def main() -> None:
    from sonarset.perf import keep_freed_memory

    keep_freed_memory()
    try:
        app()
    except Exception as exc:  # an unexpected error is a bug: say so in one line
        if os.environ.get("SONARSET_DEBUG"):
            raise
        err.print(f"[bold red]internal error:[/] {type(exc).__name__}: {exc} (set SONARSET_DEBUG=1 for details)",
                  highlight=False, soft_wrap=True)
        sys.exit(70)


if __name__ == "__main__":
    main()
