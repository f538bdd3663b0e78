"""The machine a benchmark ran on, as its results file records it: timings and bf16 arithmetic
depend on it, so files from other machines are read with it beside them."""

from __future__ import annotations

import os
import platform
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

from sonarset.version import __version__


def cpu_model() -> str:
    """The processor's marketing name (Linux ``model name``), else what the platform says."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        try:
            for line in cpuinfo.read_text(errors="replace").splitlines():
                key, _, value = line.partition(":")
                if key.strip() == "model name" and value.strip():
                    return value.strip()
        except OSError:
            pass
    return platform.processor() or platform.machine() or "unknown"


def gpu_name(device: str) -> str | None:
    if not str(device).startswith("cuda"):
        return None
    import torch

    return torch.cuda.get_device_name(torch.device(device))


def machine(device: str) -> dict:
    """CPU model, cores, bf16 flags, the device and its GPU, versions and the date (UTC)."""
    from sonarset.models.echopt.precision import cpu_bf16_flags

    try:
        torch_version = metadata.version("torch")
    except metadata.PackageNotFoundError:
        torch_version = None
    return {
        "cpu": cpu_model(), "cores": os.cpu_count(), "bf16_flags": list(cpu_bf16_flags()),
        "device": device, "gpu": gpu_name(device), "platform": platform.platform(),
        "python": platform.python_version(), "torch": torch_version, "sonarset": __version__,
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }


def describe(m: dict) -> str:
    """One line: "AMD EPYC, 2 cores (bf16: avx512_bf16), cpu, torch 2.13.0, sonarset 0.1.0, 2026-12-06"."""
    bf16 = f"bf16: {', '.join(m['bf16_flags'])}" if m.get("bf16_flags") else "no bf16 units"
    device = m.get("gpu") or m.get("device")
    return (f"{m.get('cpu')}, {m.get('cores')} cores ({bf16}), {device}, torch {m.get('torch')}, "
            f"sonarset {m.get('sonarset')}, {str(m.get('date', ''))[:10]}")
