"""``sonarset experiment slip|control``: the paper's robot experiments."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import typer
from rich.progress import Progress
from rich.table import Table

from sonarset.cli.choices import Device, Precision, value
from sonarset.cli.common import out, progress_bar, user_errors
from sonarset.cli.options import ExperimentProcessing, Model, ModelDevice, ModelPrecision, Workers
from sonarset.models.registry import model_option_spec

experiment_app = typer.Typer(help="The paper's robot experiments: wheel-slip detection, corridor control.",
                             no_args_is_help=True)


def _specs(text: str) -> list[str]:
    return [m.strip() for m in text.split(",") if m.strip()]


def _count_progress(bar: Progress, name: str) -> Callable[[int, int], None]:
    task = bar.add_task(name, total=None)
    return lambda done, total: bar.update(task, completed=done, total=total)


@experiment_app.command("slip")
@user_errors
def experiment_slip(
    out_dir: Path = typer.Option(..., "--out", help="Directory for metrics.json, report.md and fig5_slip.png."),
    model: Model = "pretrained",
    baselines: str = typer.Option("naive,flow", "--baselines",
                                  help="Comma-separated other predictors to compare (any registered name, KIND:PATH "
                                       "or package.module:factory[:ARG]; sonarset models lists the names)."),
    trials: int = typer.Option(20, "--trials", min=1, help="Random trajectories for the ROC analysis."),
    seed: int = typer.Option(0, "--seed", help="Master seed: trajectories, slip periods, sensor noise."),
    workers: Workers = None,
    processing: ExperimentProcessing = None,
    device: ModelDevice = Device("cpu"),
    precision: ModelPrecision = Precision("auto"),
    record: Path = typer.Option(None, "--record", help="Also write the paper trajectory (path, slip factors, "
                                                       "signals) as a Rerun recording (.rrd)."),
) -> None:
    """Wheel-slip detection (paper Fig. 5) and its ROC AUC over random trajectories."""
    from sonarset.models.experiments.slip import run_slip_experiment
    from sonarset.models.experiments.slip_report import write_slip_report

    models = [*_specs(baselines), model_option_spec(model)]
    with progress_bar() as bar:
        res = run_slip_experiment(models, trials=trials, seed=seed, workers=workers, device=device.value,
                                  processing=value(processing), precision=precision.value,
                                  progress=_count_progress(bar, "trajectories"))
    write_slip_report(res, out_dir)
    if record is not None:
        from sonarset.models.experiments.record import record_slip

        out.print(f"recording: {record_slip(res, record)}")
    table = Table("predictor", "horizon", "AUC both (eps)", "AUC one (eps)", "AUC both (ratio)", "AUC one (ratio)")
    by = {(x["predictor"], x["horizon"], x["kind"], x["detector"]): x["auc_mean"] for x in res.summary}
    for name in res.names:
        for h in (1, 3, 5):
            table.add_row(name, "one-shot" if h == 1 else f"AR-{h}",
                          *(f"{by[(name, h, k, d)]:.3f}" for d in ("eps", "ratio") for k in ("both", "one")))
    out.print(table)
    out.print(f"{res.trials} trajectories in {res.seconds:.0f} s; report: {out_dir / 'report.md'}")


@experiment_app.command("control")
@user_errors
def experiment_control(
    out_dir: Path = typer.Option(..., "--out", help="Directory for metrics.json, report.md and fig6_control.png."),
    model: Model = "pretrained",
    compare: str = typer.Option("flow", "--compare",
                                help="Comma-separated other predictors that also bridge the bursts ('' for none): "
                                     "any registered name, KIND:PATH or package.module:factory[:ARG]."),
    runs: int = typer.Option(50, "--runs", min=1, help="Runs per condition."),
    seed: int = typer.Option(0, "--seed", help="Master seed: spawn poses, burst schedules, sensor noise."),
    max_time: float = typer.Option(120.0, "--max-time", min=1.0, help="Seconds before a run times out."),
    workers: Workers = None,
    processing: ExperimentProcessing = None,
    device: ModelDevice = Device("cpu"),
    precision: ModelPrecision = Precision("auto"),
    record: Path = typer.Option(None, "--record", help="Also write every episode (paths, SNR, bursts, bridged "
                                                       "frames) as a Rerun recording (.rrd)."),
) -> None:
    """Corridor control through noise bursts (paper Fig. 6): clean, bursts, bursts bridged by the model
    (the recommended one, EchoWarp, by default)."""
    from sonarset.models.experiments.control import run_control_experiment
    from sonarset.models.experiments.control_report import write_control_report

    models = [model_option_spec(model), *_specs(compare)]
    with progress_bar() as bar:
        res = run_control_experiment(models, runs=runs, seed=seed, workers=workers, device=device.value,
                                     processing=value(processing), max_time_s=max_time, precision=precision.value,
                                     progress=_count_progress(bar, "runs"))
    write_control_report(res, out_dir)
    if record is not None:
        from sonarset.models.experiments.record import record_control

        out.print(f"recording: {record_control(res, record)}")
    table = Table("condition", "success", "collision", "timeout", "travel time [s]", "midline dev. [m]")
    for c, x in res.summary.items():
        table.add_row(c, str(x["success"]), str(x["collision"]), str(x["timeout"]),
                      f"{x['travel_time_s']['mean']:.1f}", f"{x['midline_deviation_m']['mean']:.3f}")
    out.print(table)
    out.print(f"{runs} runs per condition in {res.seconds:.0f} s; report: {out_dir / 'report.md'}")
