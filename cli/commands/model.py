"""``sonarset eval|train|demo|export-onnx``: the predictors, EchoPT's training and its exports."""

from __future__ import annotations

import contextlib
import enum
import os
from pathlib import Path
from typing import Optional

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from sonarset.errors import SonarSetError
from sonarset.models.echopt.train_config import TrainConfig
from sonarset.models.registry import BASELINES, HORIZONS

from sonarset.cli.choices import (Device, ModelKind, Optimizer, Precision, Inputs, Prior, Schedule, StepWeights,
                                  Trainable)
from sonarset.cli.common import err, fail, out, per_name_progress, progress_bar, user_errors
from sonarset.cli.options import Model, ModelDevice, ModelPrecision


#: The defaults of ``sonarset train``: TrainConfig's (its ``command`` aside).
TRAIN = TrainConfig(command="")


def _int_list(text: str, what: str) -> list[int]:
    try:
        values = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        fail(f"{what} must be comma-separated integers, got {text!r}", 2)
    if not values or min(values) < 1:
        fail(f"{what} must be positive integers, got {text!r}", 2)
    return values


@user_errors
def eval_(
    store: str = typer.Argument(..., help="Store path or fsspec URL."),
    models: str = typer.Option(",".join(BASELINES), "--models",
                               help="Comma-separated predictors: any registered name (persistence, naive, flow, "
                                    "pretrained, a plugin's; sonarset models lists them), KIND:PATH "
                                    "(echopt:run/model.safetensors, echopt:model.onnx, echopt:pretrained) or "
                                    "package.module:factory[:ARG]."),
    horizons: str = typer.Option(",".join(map(str, HORIZONS)), "--horizons", help="Prediction horizons (1 = one-shot)."),
    samples: int = typer.Option(1000, "--samples", min=1, help="Windows drawn (seeded), shared by all methods."),
    out_dir: Path = typer.Option(Path("eval-out"), "--out",
                                 help="Directory for metrics.json, per_window.csv, report.md, figures."),
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
    stream: bool = typer.Option(False, "--stream", help="Read only the frames of the drawn windows, not every frame "
                                                         "of the split: memory bounded by --samples, not the store."),
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
                       ceiling=ceiling, worlds=[w.strip() for w in worlds.split(",") if w.strip()] or None,
                       stream=stream)
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


#: Recipe keys whose ``train`` parameter is spelled otherwise (the rest are the parameters' names).
_RECIPE_PARAMETERS = {"out": "out_dir", "compile": "compile_"}


def _recipe_values(ctx: typer.Context, path: Path) -> dict:
    """The settings of the recipe at ``path`` that the command line does not give, each checked as its
    option checks it (choices, ranges)."""
    from sonarset.models.echopt.recipes import dump_recipe, load_recipe

    params = {p.name: p for p in ctx.command.params}
    taken = {}
    for key, setting in load_recipe(path).items():
        name = _RECIPE_PARAMETERS.get(key, key)
        source = ctx.get_parameter_source(name)
        if source is not None and source.name == "COMMANDLINE":
            continue  # a flag given overrides the file
        if setting != getattr(TRAIN, key, None):  # a default needs no check (prior "" is no choice)
            try:
                params[name].process_value(ctx, setting)
            except typer.BadParameter as exc:
                raise SonarSetError(f"{path}: {dump_recipe({key: setting}).strip()}: {exc.message}") from None
        taken[key] = setting
    return taken


def _train_settings(ctx: typer.Context, config: Optional[Path]) -> dict:
    """The run's recipe: each option's value from the command line where given, else from the recipe
    file, else the option's default."""
    from sonarset.models.echopt.recipes import RECIPE_KEYS

    settings = {key: _setting(key, ctx.params[_RECIPE_PARAMETERS.get(key, key)]) for key in RECIPE_KEYS}
    if config is not None:
        settings.update(_recipe_values(ctx, config))
    for key, what in (("store", "STORE"), ("out", "--out")):
        if settings[key] is None:
            fail(f"missing {what}: give it on the command line, or as {key} in a recipe (--config)", 2)
    _check_preset(ctx, config, settings["model"], settings["preset"])
    return settings


def _check_preset(ctx: typer.Context, config: Optional[Path], model: str, preset: str) -> None:
    """A preset the network lacks is a usage error, named where it was given, before any file is read
    (each network has its own presets, so typer cannot list them as a closed choice)."""
    from sonarset.models.echopt.networks import preset_refusal
    from sonarset.models.echopt.recipes import dump_recipe

    why = preset_refusal(model, preset)
    if why is None:
        return
    given = ctx.get_parameter_source("preset")
    if config is None or (given is not None and given.name == "COMMANDLINE"):
        fail(f"--preset {preset}: {why}", 2)
    raise SonarSetError(f"{config}: {dump_recipe({'preset': preset}).strip()}: {why}")


def _setting(key: str, given):
    """An option's value as a recipe holds it: a choice as its string, a path as a string, and no
    value (options whose default is "the preset's") as TrainConfig's default."""
    if given is None:
        return getattr(TRAIN, key, None)
    if isinstance(given, enum.Enum):
        return given.value
    return str(given) if isinstance(given, Path) else given


@user_errors
def train(
    ctx: typer.Context,
    store: Optional[str] = typer.Argument(None, metavar="STORE",
                                          help="Training store (its 'train' split; 'test' is never used for "
                                               "training). Default: the recipe's."),
    config: Optional[Path] = typer.Option(None, "--config", help="A recipe: a TOML file of these options, keys "
                                                                 "spelled with underscores (max_steps = 2), also "
                                                                 "store and out; options given here override it "
                                                                 "(docs/guides/training.md)."),
    model: ModelKind = typer.Option(TRAIN.model, "--model",
                                    help="The network: echopt (the paper's), echowarp (sonarset's own, "
                                         "docs/echowarp.md), or a reference method of video prediction: "
                                         "convlstm, simvp, unet (models/zoo/)."),
    preset: str = typer.Option(TRAIN.preset, "--preset",
                               help="The network's size or variant: small (trains on a CPU), tiny (tests); EchoPT "
                                    "also paper (~9 M parameters), EchoWarp also wide, patch4 (every "
                                    "convolution at 1/4 resolution) and its ablation variants "
                                    "(docs/echowarp.md). A preset the network lacks is refused with its list."),
    out_dir: Optional[Path] = typer.Option(None, "--out", help="Run directory: model.safetensors + model.json, "
                                                               "metrics.jsonl, state.safetensors. Default: the "
                                                               "recipe's."),
    epochs: int = typer.Option(TRAIN.epochs, "--epochs", min=1, help="Passes over the training windows (paper: 1000)."),
    batch_size: int = typer.Option(TRAIN.batch_size, "--batch-size", min=1),
    lr: float = typer.Option(TRAIN.lr, "--lr", help="Adam learning rate (paper: 5e-5)."),
    weight_decay: float = typer.Option(TRAIN.weight_decay, "--weight-decay", help="L2 regularisation (paper: 1e-4)."),
    optimizer: Optimizer = typer.Option(TRAIN.optimizer, "--optimizer",
                                        help="adam (paper: L2 in the gradient) or adamw (decoupled decay; use it "
                                             "with a prior)."),
    schedule: Schedule = typer.Option(TRAIN.schedule, "--schedule", help="none (paper) or cosine."),
    seed: int = typer.Option(TRAIN.seed, "--seed"),
    device: Device = typer.Option(TRAIN.device, "--device"),
    precision: ModelPrecision = Precision(TRAIN.precision),
    resume: bool = typer.Option(False, "--resume", help="Continue a killed run exactly where it stopped (give the "
                                                        "same options, or the same recipe)."),
    eval_every: int = typer.Option(TRAIN.eval_every, "--eval-every", min=0,
                                   help="Steps between validations/checkpoints (0: each epoch)."),
    max_steps: int = typer.Option(TRAIN.max_steps, "--max-steps", min=0, help="Stop after this many steps (0: no limit)."),
    max_minutes: float = typer.Option(TRAIN.max_minutes, "--max-minutes", min=0.0,
                                      help="Stop after this wall time (0: no limit)."),
    compile_: bool = typer.Option(TRAIN.compile, "--compile/--no-compile", help="torch.compile the model (GPU)."),
    test_samples: int = typer.Option(TRAIN.test_samples, "--test-samples", min=0,
                                     help="Test windows for the card's metrics (0: skip)."),
    n_val: int = typer.Option(TRAIN.n_val, "--n-val", min=1, help="Random validation windows (paper: 1600)."),
    prior: Optional[Prior] = typer.Option(None, "--prior", help="What the model corrects: none (paper), last (frame) "
                                                                 "or flow (its acoustic-flow warp). Default: the "
                                                                 "preset's (paper none, small flow)."),
    loss: str = typer.Option(TRAIN.loss, "--loss", help="mse, l1, gdl (image-gradient difference), cc (1 - CC), "
                                                        "nrmsd (the evaluation's NRMSD per image), "
                                                        "nrmsd_pooled (summed error norms over summed target "
                                                        "norms: every image pulls alike), nrmsd_floored "
                                                        "(per image, no target counted below a quarter of "
                                                        "the batch's median norm), nrmsd_capped (per "
                                                        "image, weight capped where flow's NRMSD is above "
                                                        "2), w1 (1-D "
                                                        "Wasserstein of the pixel values), energy (the batch's "
                                                        "echo-energy deficit), echo (hinges on missed and false "
                                                        "echoes, the echo F1's matching), or a weighted sum: "
                                                        "cc=1,w1=50."),
    curriculum: str = typer.Option(TRAIN.curriculum, "--curriculum",
                                   help="Rollout steps k of the unrolled loss: k, or step:k,... "
                                        "(e.g. 0:1,300:2,600:4,900:6)."),
    pushforward: bool = typer.Option(TRAIN.pushforward, "--pushforward/--no-pushforward",
                                     help="Only the last rollout step carries gradient."),
    step_weights: StepWeights = typer.Option(TRAIN.step_weights, "--step-weights",
                                             help="The rollout steps' shares of the loss: uniform (1/k each) or "
                                                  "harmonic (step h by 1/h: more weight on the first forecasts)."),
    horizons: str = typer.Option(TRAIN.horizons, "--horizons",
                                 help="The rollout steps that carry the loss, e.g. 1,3,5,10 (default: every step); a "
                                      "model that forecasts each horizon directly (EchoWarp) computes those alone, "
                                      "within its max horizon."),
    context_noise: float = typer.Option(TRAIN.context_noise, "--context-noise", min=0.0,
                                        help="Std of Gaussian noise on the context frames."),
    val_horizon: int = typer.Option(TRAIN.val_horizon, "--val-horizon", min=0,
                                    help="Rollout steps of the validation loss (0: the curriculum's longest)."),
    init: str = typer.Option(TRAIN.init, "--init", help="Fine-tune: start from this checkpoint's weights (pretrained, "
                                                        "a run directory or a path, also as KIND:RUN; same kind, "
                                                        "preset, prior, grid and images); the optimizer starts "
                                                        "fresh."),
    worlds: str = typer.Option(TRAIN.worlds, "--worlds", help="Train only on runs of these world families, "
                                                              "comma-separated (e.g. lab,orchard; default: every "
                                                              "training run)."),
    n_in: int = typer.Option(TRAIN.n_in, "--n-in", min=0, help="Input frames per window (0: the preset's, the "
                                                               "paper's 3)."),
    inputs: Optional[Inputs] = typer.Option(None, "--inputs", help="raw (paper: the frames as measured) or aligned "
                                                                   "(each warped to the predicted frame's pose along "
                                                                   "the commands). Default: the preset's (raw), or "
                                                                   "--init's model's."),
    geometry_channels: Optional[int] = typer.Option(None, "--geometry-channels", min=0,
                                                    help="Channels of the geometry branch: frame filters weighted "
                                                         "per pixel by its position and the command's warp (0: "
                                                         "none, the paper's). A fine-tune may add it to a model "
                                                         "without one. Default: the preset's (0), or --init's "
                                                         "model's."),
    trainable: Trainable = typer.Option(TRAIN.trainable, "--trainable",
                                        help="all, or geometry: only the geometry branch learns, the rest "
                                             "stays as --init trained it."),
    stream: bool = typer.Option(TRAIN.stream, "--stream/--no-stream",
                                help="Stream windows from the store instead of loading all its frames: for stores "
                                     "bigger than memory, or behind a URL (docs/scaling.md)."),
    shuffle_buffer: int = typer.Option(TRAIN.shuffle_buffer, "--shuffle-buffer", min=1,
                                       help="With --stream: windows mixed at once (memory: ~36 MB per 1000 on the "
                                            "default grid)."),
    loader_workers: int = typer.Option(TRAIN.loader_workers, "--workers", "--loader-workers", min=0,
                                       help="With --stream: DataLoader worker processes reading the store (0: this "
                                            "one)."),
) -> None:
    """Train a predictor (EchoPT, EchoWarp or a reference method); the best validation weights are
    kept as OUT/model.safetensors with a model card.

    The options may come from a recipe file (--config RECIPE.toml); the card records the whole recipe.

    Killed at any point, the same command with --resume continues exactly (OUT/state.safetensors)."""
    # the options are read by name from ctx.params, so a recipe's keys and the options are one list
    from sonarset.models.echopt.cards import add_test_metrics
    from sonarset.models.echopt.recipes import config_of
    from sonarset.models.echopt.train import train as run_training
    from sonarset.store.store import open_store

    settings = _train_settings(ctx, config)
    out_dir = Path(settings["out"])
    s = open_store(settings["store"], check=True)
    cfg = config_of(settings)
    main = int(os.environ.get("RANK", "0")) == 0  # under torchrun only rank 0 reports
    _print_notes(cfg.notes() if main else [])
    with _training_bar(main) as progress:
        res = run_training(s, out_dir, cfg, resume=resume, progress=progress)
    if not main:
        return
    weights = out_dir / "model.safetensors"
    kept = f"weights: {weights}" if weights.is_file() else "no weights kept (no validation loss was finite)"
    out.print(f"{res.steps} steps ({res.epochs_done:.2f} epochs); best validation loss {res.best_val_loss:.6f}; {kept}")
    if cfg.test_samples and s.runs("test"):
        test = add_test_metrics(out_dir, s, cfg)
        r = test["results"]
        for m in ("flow", test["model"]):
            one = r[m]["1"]
            out.print(f"test one-shot {m}: CC {_mean(one['cc'])}, NRMSD {_mean(one['nrmsd'])}")


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
    """Simulate a fresh test run and compare a model (the recommended pretrained one, EchoWarp, by
    default) with persistence, naive and flow (and the noise and observable ceilings)."""
    import time

    from sonarset.models import demo as pipeline
    from sonarset.models.eval.report import results_table, write_report
    from sonarset.models.registry import model_option_spec

    spec = model_option_spec(model)
    # a bad model fails now, not after the simulation
    predictor = pipeline.check_model(spec, device.value, precision.value)
    t0 = time.perf_counter()
    store_path = out_dir / "test.zarr"
    out.print(f"simulating a fresh {minutes:g}-minute test run (seed {seed}) -> {store_path}")
    with progress_bar() as bar:
        task = bar.add_task("simulating", total=None)
        s = pipeline.simulate_fresh_run(store_path, minutes=minutes, seed=seed,
                                        progress=lambda name, done, total: bar.update(task, completed=done, total=total))
    for line in (pipeline.images_note(predictor, s), pipeline.runs_in(predictor, precision.value, device.value)):
        if line:
            out.print(line, highlight=False)
    out.print(f"evaluating {', '.join(BASELINES)} and {pipeline.title(predictor.name)} ({model}) on {samples} windows, "
              f"horizons {', '.join(map(str, HORIZONS))}, "
              "with the noise and observable ceilings")
    with progress_bar() as bar:
        res = pipeline.evaluate_fresh_run(s, spec, samples=samples, device=device.value, precision=precision.value,
                                          progress=per_name_progress(bar))
    write_report(res, out_dir)
    _print_notes(res.notes)
    out.print(results_table(res, with_paper=True))
    for line in pipeline.model_against_flow(res):
        out.print(line)
    out.print(f"report: {out_dir / 'report.md'} (figures beside it); {time.perf_counter() - t0:.0f} s in all")


@user_errors
def export_onnx_(
    model: str = typer.Argument(..., metavar="MODEL", help="pretrained (the recommended shipped model), "
                                                          "KIND:pretrained, an EchoPT run directory or .safetensors "
                                                          "path, or EchoWarp's as echowarp:RUN."),
    out_path: Path = typer.Argument(..., metavar="OUT.onnx", help="The ONNX file to write."),
) -> None:
    """Export EchoPT or EchoWarp to ONNX for onnxruntime: a dynamic batch axis (EchoWarp's graph forecasts the
    horizons it is given), the flow geometry inside the graph, the model card in the metadata; checked against
    torch before it is written."""
    from sonarset.models.echopt.onnx_export import export_onnx

    e = export_onnx(model, out_path)
    out.print(f"wrote {e.path} ({e.bytes / 1e6:.1f} MB)", highlight=False)
    if e.max_abs_diff is None:
        out.print("note: onnxruntime is not installed, so the export was not run; pip install 'sonarset[onnx]'",
                  style="yellow", highlight=False)
    else:
        out.print(f"onnxruntime matches torch to {e.max_abs_diff:.1e} (max abs) on {e.check_windows} random windows",
                  highlight=False)
    out.print(f"use it as --models {e.kind}:{e.path} (eval) or --model {e.kind}:{e.path} (demo, experiments)",
              highlight=False)
