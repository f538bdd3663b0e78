"""Arguments and options that several commands share, each with one help text."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from sonarset.cli.choices import Device, Precision, ProcessingProfile

OutStore = Annotated[str, typer.Argument(metavar="OUT", help="Store to create or append to.")]
MetaPath = Annotated[Optional[Path], typer.Option("--meta", help="Metadata (sidecar) JSON (default: SRC.json / "
                                                                   "SRC/recording.json).")]
RunName = Annotated[Optional[str], typer.Option("--name", help="Run name (default: the metadata's name, else the "
                                                               "file stem).")]
RunSplit = Annotated[Optional[str], typer.Option("--split", help="Split of the run (default: the metadata's split).")]
Overwrite = Annotated[bool, typer.Option("--overwrite", help="Replace a run of the same name (only once the new one "
                                                             "is complete).")]
Model = Annotated[str, typer.Option("--model", help="The model: any registered name (pretrained, the recommended "
                                                    "shipped one; flow; a plugin's; sonarset models lists them), "
                                                    "KIND:PATH (echopt:run/model.safetensors, .onnx) or "
                                                    "package.module:factory[:ARG]. A bare path is an EchoPT checkpoint.")]
Workers = Annotated[Optional[int], typer.Option("--workers", min=1, help="Processes (default: all cores).")]
ModelDevice = Annotated[Device, typer.Option("--device", help="Device for learned models.")]
ExperimentProcessing = Annotated[Optional[ProcessingProfile], typer.Option(
    "--processing", help="Images to simulate. Default: those the model was trained on (its card); a "
                         "different profile is refused.")]
ModelPrecision = Annotated[Precision, typer.Option(
    "--precision", help="Learned models' arithmetic: auto (bf16 autocast where the CPU has bf16 units or on a GPU, "
                        "else fp32), fp32 or bf16. ONNX models run in fp32.")]
