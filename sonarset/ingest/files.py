"""The files of a recording: regular files only, and the arrays of a ``.npz`` or of a directory
of ``.npy`` files, read whole (``read_arrays``) or lazily, block by block (``RawSource``).

Only regular files are opened: a FIFO would block, a device never end.
"""

from __future__ import annotations

import os
import stat
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np


def read_arrays(src: Path) -> tuple[dict[str, Any], Any, list[str]]:
    """The arrays of ``src`` (a ``.npz``, or a directory of ``.npy`` files, memory-mapped), the
    ``.npz``'s own ``metadata`` array if it has one (else None), and a line per problem reading them."""
    problems: list[str] = []
    arrays: dict[str, Any] = {}
    if src.is_dir():
        for path in sorted(src.glob("*.npy")):
            irregular = regular_file_problem(path)
            if irregular:
                problems.append(f"{path.name}: {irregular}")
                continue
            try:
                arrays[path.stem] = np.load(path, allow_pickle=False, mmap_mode="r")
            except Exception as exc:
                problems.append(f"{path.name}: not a readable .npy file ({short_reason(exc)})")
        if not arrays and not problems:
            problems.append("directory holds no .npy files")
        return arrays, None, problems
    if src.suffix != ".npz":
        return arrays, None, ["unsupported input (expected a .npz file or a directory of .npy files)"]
    try:
        with np.load(src, allow_pickle=False) as npz:
            for key in npz.files:
                try:
                    arrays[key] = npz[key]
                except Exception as exc:
                    problems.append(f"array {key!r}: unreadable ({short_reason(exc)})")
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        return {}, None, [f"not a readable .npz file ({short_reason(exc)})"]
    return arrays, arrays.pop("metadata", None), problems


def short_reason(exc: Exception) -> str:
    """The first line of an error's message (at most 160 characters), for a line naming the file."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text[:160]


def regular_file_problem(path: Path) -> str | None:
    """Why ``path`` must not be opened (a FIFO would block, a device never end), else None."""
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    if stat.S_ISREG(mode):
        return None
    kind = ("a directory" if stat.S_ISDIR(mode) else "a FIFO (named pipe)" if stat.S_ISFIFO(mode)
            else "a socket" if stat.S_ISSOCK(mode) else "a character device" if stat.S_ISCHR(mode)
            else "a block device" if stat.S_ISBLK(mode) else "not a plain file")
    return f"not a regular file ({kind}); only regular files are imported"


@dataclass
class ArrayMember:
    """One array of the input: its header, and how to read it."""

    shape: tuple
    dtype: np.dtype
    fortran: bool
    path: Path  # the .npy, or the .npz holding it
    member: str | None = None  # name inside the .npz


def _npy_header(f) -> tuple[tuple, bool, np.dtype]:
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        return np.lib.format.read_array_header_1_0(f)
    if version == (2, 0):
        return np.lib.format.read_array_header_2_0(f)
    raise ValueError(f"unsupported .npy format version {version}")


class RawSource:
    """The arrays of a ``.npz`` or of a directory of ``.npy`` files, read lazily."""

    def __init__(self, src: Path):
        self.src = src
        self.members: dict[str, ArrayMember] = {}
        self.problems: list[str] = []
        if src.is_dir():
            for path in sorted(src.glob("*.npy")):
                try:
                    with open(path, "rb") as f:
                        shape, fortran, dtype = _npy_header(f)
                        offset = f.tell()
                    need = offset + int(np.prod(shape)) * dtype.itemsize
                    if path.stat().st_size < need:
                        raise ValueError(f"truncated: {path.stat().st_size} bytes, the header needs {need}")
                    self.members[path.stem] = ArrayMember(tuple(shape), dtype, fortran, path)
                except Exception as exc:
                    self.problems.append(f"{path.name}: not a readable .npy file ({short_reason(exc)})")
            if not self.members and not self.problems:
                self.problems.append("directory holds no .npy files")
        elif src.suffix != ".npz":
            self.problems.append("unsupported input (expected a .npz file or a directory of .npy files)")
        else:
            try:
                with zipfile.ZipFile(src) as zf:
                    for info in zf.infolist():
                        if not info.filename.endswith(".npy"):
                            continue
                        key = info.filename[:-4]
                        try:
                            with zf.open(info) as f:
                                shape, fortran, dtype = _npy_header(f)
                            self.members[key] = ArrayMember(tuple(shape), dtype, fortran, src, info.filename)
                        except Exception as exc:
                            self.problems.append(f"array {key!r}: unreadable ({short_reason(exc)})")
            except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
                self.problems.append(f"not a readable .npz file ({short_reason(exc)})")

    def read(self, key: str) -> np.ndarray:
        """A whole (small) array."""
        m = self.members[key]
        if m.member is None:
            return np.load(m.path, allow_pickle=False)
        with zipfile.ZipFile(m.path) as zf, zf.open(m.member) as f:
            return np.lib.format.read_array(f, allow_pickle=False)

    def blocks(self, key: str, block: int, start: int = 0) -> Iterator[tuple[int, np.ndarray]]:
        """(first index, rows) of ``key`` from ``start``, ``block`` rows at a time, never more in memory."""
        m = self.members[key]
        T = m.shape[0]
        row = int(np.prod(m.shape[1:])) * m.dtype.itemsize
        if m.member is None:
            arr = np.load(m.path, mmap_mode="r", allow_pickle=False)
            for i in range(start, T, block):
                yield i, np.array(arr[i:i + block])
            return
        with zipfile.ZipFile(m.path) as zf, zf.open(m.member) as f:
            _npy_header(f)
            left = start * row
            while left > 0:  # a sequential archive member: skip by reading
                left -= len(f.read(min(left, 1 << 24)))
            for i in range(start, T, block):
                n = min(block, T - i)
                buf = f.read(n * row)
                if len(buf) != n * row:
                    raise EOFError(f"{key}: the archive ends inside measurement {i + len(buf) // max(row, 1)}")
                yield i, np.frombuffer(buf, m.dtype).reshape(n, *m.shape[1:])
