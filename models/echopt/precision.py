"""Where and in what precision EchoPT runs: the device (``DEVICES``), and fp32 or bf16 autocast where
the hardware has bf16 units (``PRECISIONS``).

``auto`` (the default everywhere) picks bf16 on a GPU that supports it and on a CPU whose
instruction set has bf16 matrix or dot-product units (x86 ``amx_bf16`` or ``avx512_bf16``, Arm
``bf16``), read from the processor's own flags; elsewhere fp32. bf16 on a CPU without such units
still runs (oneDNN emulates it), only slower than fp32, so ``auto`` never picks it there.

Under bf16 autocast, matrix products and convolutions run in bf16 and everything numerically
delicate (layer norms, softmax statistics, the flow prior's geometry, the losses) stays in fp32;
BENCHMARKS.md measures what that changes in the scores (<= 0.002 CC or NRMSD on the shipped model).

torch is imported where it is used: the command line lists the devices and precisions from here
without loading it.
"""

from __future__ import annotations

import contextlib
import functools
import platform
import subprocess
from pathlib import Path
from typing import TYPE_CHECKING

from sonarset.errors import SonarSetError

if TYPE_CHECKING:
    import torch

#: ``auto``: CUDA where there is a device, else the CPU; ``cuda:N`` is taken as well (one of several GPUs).
DEVICES = ("auto", "cpu", "cuda")
PRECISIONS = ("auto", "fp32", "bf16")
#: CPU flags that mean native bf16 arithmetic: Intel AMX tiles, AVX-512 BF16 dot products (Intel
#: Cooper Lake and later, AMD Zen 4 and later), the Armv8.6 BF16 extension (Linux names it ``bf16``).
CPU_BF16_FLAGS = ("amx_bf16", "avx512_bf16", "bf16")


def bf16_flags_in(cpuinfo: str) -> tuple[str, ...]:
    """The bf16 flags in the text of a Linux ``/proc/cpuinfo`` (x86 ``flags``, aarch64 ``Features`` lines)."""
    found: set[str] = set()
    for line in cpuinfo.splitlines():
        key, _, rest = line.partition(":")
        if key.strip().lower() in ("flags", "features"):
            found.update(f for f in rest.split() if f in CPU_BF16_FLAGS)
    return tuple(f for f in CPU_BF16_FLAGS if f in found)


@functools.cache
def cpu_bf16_flags() -> tuple[str, ...]:
    """The bf16 flags this machine's CPU reports (empty where it has none or does not say)."""
    found: set[str] = set()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        try:
            found.update(bf16_flags_in(cpuinfo.read_text(errors="replace")))
        except OSError:
            pass
    elif platform.system() == "Darwin":
        try:
            out = subprocess.run(["sysctl", "-n", "hw.optional.arm.FEAT_BF16"], capture_output=True, text=True,
                                 timeout=5).stdout.strip()
            if out == "1":
                found.add("bf16")
        except (OSError, subprocess.SubprocessError):
            pass
    return tuple(f for f in CPU_BF16_FLAGS if f in found)


def resolve_precision(precision: str, device: str) -> str:
    """``fp32`` or ``bf16`` for ``precision`` (auto, fp32, bf16) on ``device`` (cpu, cuda, cuda:N)."""
    import torch

    if precision not in PRECISIONS:
        raise SonarSetError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}", parameter="precision")
    if precision != "auto":
        return precision
    if str(device).startswith("cuda"):
        return "bf16" if torch.cuda.is_available() and torch.cuda.is_bf16_supported() else "fp32"
    return "bf16" if cpu_bf16_flags() and torch.backends.mkldnn.is_available() else "fp32"


def autocast(device: str | torch.device, precision: str) -> contextlib.AbstractContextManager:
    """The context EchoPT runs in at a resolved ``precision``: bf16 autocast, or nothing for fp32."""
    if precision == "fp32":
        return contextlib.nullcontext()
    import torch

    return torch.autocast(torch.device(device).type, dtype=torch.bfloat16)


def describe_precision(precision: str, device: str) -> str:
    """Why ``auto`` chose what it did, in a phrase: "bf16 (CPU flags avx512_bf16)"."""
    chosen = resolve_precision(precision, device)
    if precision != "auto":
        return chosen
    if str(device).startswith("cuda"):
        return f"{chosen} (GPU)"
    flags = cpu_bf16_flags()
    return f"{chosen} (CPU flags {', '.join(flags)})" if flags else f"{chosen} (no bf16 units in this CPU)"


def resolve_device(device: str) -> str:
    """The device ``device`` (one of DEVICES, or cuda:N) stands for on this machine."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise SonarSetError("device cuda: no CUDA device is available", parameter="device")
    return device
