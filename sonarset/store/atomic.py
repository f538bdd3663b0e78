"""Atomic file writes: a reader sees the old file or the new one, never half of either."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable


def _umask() -> int:
    """The process's umask, read without changing it (os.umask can only set it, which races threads)."""
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1], 8) for line in f if line.startswith("Umask:"))
    except (OSError, StopIteration, ValueError, IndexError):
        return 0o022


def atomic_write(path: str | os.PathLike, write: Callable[[Path], object]) -> Path:
    """Call ``write(tmp)`` on a hidden file beside ``path``, then rename it over ``path``, with the
    permissions a plain file gets (some writers, safetensors' among them, create theirs 0600)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def refuse_non_regular(out: Path, what: str, needs: str) -> None:
    """Only a regular file is replaced: a folder, a FIFO or a device at ``out`` is the user's, and a
    rename over it would fail naming the hidden file it was written to (or a FIFO would block).
    ``what`` names the output in messages ("the recording"), ``needs`` what the path must be
    ("the recording needs a .rrd file path")."""
    import stat

    from sonarset.errors import SonarSetError

    try:
        mode = out.stat().st_mode
    except FileNotFoundError:
        return
    except OSError as exc:
        raise SonarSetError(f"{out}: cannot write {what} there ({exc.strerror})", parameter="out") from None
    if not stat.S_ISREG(mode):
        kind = "a folder" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else "not a regular file"
        raise SonarSetError(f"{out}: is {kind}; {needs}", parameter="out")


def atomic_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write(path, lambda p: p.write_text(text))


def save_figure(fig, path: str | os.PathLike, dpi: int = 100) -> Path:
    """Save a matplotlib figure atomically and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    try:
        return atomic_write(path, lambda p: fig.savefig(p, dpi=dpi, format=path.suffix.lstrip(".") or "png"))
    finally:
        plt.close(fig)


# ---- directories built aside ------------------------------------------------------------------
# A store (or a run) is built in a hidden directory beside its destination and renamed into place,
# so a reader, or a writer killed at any moment, never leaves a half-made one where it belongs.
# The directory's name carries the host and process id: a later writer removes leftovers of dead
# processes on this host and leaves a live writer's alone.

def _aside_prefix(dest: Path) -> str:
    return f".{dest.name}."


def aside_dir(dest: str | os.PathLike) -> Path:
    """A new, empty hidden directory beside ``dest`` (same file system, so a rename can move it)."""
    import socket
    import tempfile

    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_asides(dest)
    host = "".join(c if c.isalnum() or c == "-" else "_" for c in socket.gethostname())[:40] or "host"
    return Path(tempfile.mkdtemp(prefix=f"{_aside_prefix(dest)}{host}-{os.getpid()}-", suffix=".tmp", dir=dest.parent))


def remove_stale_asides(dest: str | os.PathLike) -> list[Path]:
    """Remove the aside directories of ``dest`` left by killed processes of this host."""
    import re
    import shutil
    import socket

    dest = Path(dest)
    host = "".join(c if c.isalnum() or c == "-" else "_" for c in socket.gethostname())[:40] or "host"
    pattern = re.compile(re.escape(_aside_prefix(dest)) + re.escape(host) + r"-(\d+)-[^/]*\.tmp")
    removed = []
    try:
        entries = list(dest.parent.iterdir())
    except OSError:
        return removed
    for entry in entries:
        m = pattern.fullmatch(entry.name)
        if m is None or not entry.is_dir() or _alive(int(m.group(1))):
            continue
        if any(p.name.endswith(".old") for p in entry.glob("*/*")):
            continue  # the run an interrupted two-rename swap took out (exchange): never delete it
        shutil.rmtree(entry, ignore_errors=True)
        removed.append(entry)
    return removed


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def publish_files(out: str | os.PathLike, write: Callable[[Path], object], *, last: str) -> Path:
    """Write a set of files (a report) into the directory ``out`` as one unit.

    ``write(folder)`` makes them in a hidden directory beside ``out``. A new ``out`` is that
    directory renamed into place. Into an existing one, which may hold files of its own (the demo's
    store), the files move with ``last`` (the file that says the set is whole: report.md) removed
    first and renamed in last: a reader, or a kill at any moment, never finds ``last`` beside files
    of another set. What a killed writer left aside is removed by the next one (``aside_dir``).
    """
    import shutil

    from sonarset.errors import SonarSetError

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise SonarSetError(f"{out}: exists and is not a folder; the report needs a folder")
    aside = aside_dir(out)
    try:
        write(aside)
        if not (aside / last).is_file():
            raise FileNotFoundError(f"{aside / last}: the set's last file was not written")
        umask = os.umask(0)
        os.umask(umask)
        aside.chmod(0o777 & ~umask)  # a directory as mkdir makes it, not mkdtemp's private one
        try:
            os.rename(aside, out)  # a new (or empty) directory: the whole set at once
            return out
        except OSError:
            if not out.is_dir():
                raise
        (out / last).unlink(missing_ok=True)
        for name in sorted(p.name for p in aside.iterdir() if p.name != last):
            os.replace(aside / name, out / name)
        os.replace(aside / last, out / last)
        return out
    finally:
        shutil.rmtree(aside, ignore_errors=True)


def exchange(a: str | os.PathLike, b: str | os.PathLike) -> None:
    """Swap the directories ``a`` and ``b`` in one atomic step: a reader sees either, never neither.

    Linux's ``renameat2(RENAME_EXCHANGE)`` does it; where the kernel, the C library or the file
    system lacks it, two renames do, and on failure of the second the first is undone. A kill
    between them leaves ``b``'s old directory at ``a`` + ".old"; ``remove_stale_asides`` keeps an
    aside directory holding one, for the user to recover.
    """
    a, b = os.fsencode(os.fspath(a)), os.fsencode(os.fspath(b))
    if _renameat2_exchange(a, b):
        return
    hold = a + b".old"
    os.rename(b, hold)
    try:
        os.rename(a, b)
    except BaseException:
        os.rename(hold, b)
        raise
    os.rename(hold, a)


def _renameat2_exchange(a: bytes, b: bytes) -> bool:
    import ctypes
    import errno
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2  # glibc >= 2.28
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if fn(at_fdcwd, a, at_fdcwd, b, rename_exchange) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False
    raise OSError(code, os.strerror(code), os.fsdecode(b))


def settle_zarr_writes(timeout_s: float = 30.0) -> None:
    """Wait for the writes zarr still has in flight after one of them failed.

    zarr writes an array's chunks concurrently, each in a thread; when one fails (a full disk) the
    error surfaces at once while the others go on. Left alone they recreate folders after the
    caller removed them, and their own errors end up logged as asyncio tracebacks ("Task exception
    was never retrieved"). This awaits them on zarr's loop and retrieves their errors.
    """
    import asyncio

    from zarr.core.sync import sync

    async def settle() -> None:
        me = asyncio.current_task()
        tasks = [t for t in asyncio.all_tasks() if t is not me]
        if tasks:
            await asyncio.wait(tasks, timeout=timeout_s)
        for t in tasks:
            if t.done() and not t.cancelled():
                t.exception()

    sync(settle())
