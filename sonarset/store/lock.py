"""One writer at a time on a local store (spec/FORMAT.md §5).

A writer (generate, import, import-raw, consolidating validate) holds an advisory lock on a file
beside the store, ``.<store name>.lock``, for as long as it writes; a second writer is refused in
one line naming the holder. The lock is the kernel's (``flock``): it goes when its process does,
killed or not, so a lock is never stale; the file holds the holder's pid, host and start for the
message, and goes when the writer finishes (a killed writer's stays, unlocked, until the next).
URLs (object stores, servers) have no such lock: their writers must be one by arrangement. Where
the lock file cannot be made (a read-only folder), nothing can be written either, and writers go
on without it (a read-only store still reads, and a writer with nothing to do still succeeds).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import socket
import time
from pathlib import Path
from typing import Iterator

from sonarset.errors import SonarSetError
from sonarset.store.zarrio import is_url

try:
    import fcntl
except ImportError:  # Windows: no flock; writers go unlocked there
    fcntl = None


def lock_path(location: str | os.PathLike) -> Path:
    path = Path(os.fspath(location).removeprefix("file://")).absolute()
    return path.parent / f".{path.name}.lock"


@contextlib.contextmanager
def writer_lock(location: str | os.PathLike) -> Iterator[None]:
    """Hold the store's writer lock for the block; SonarSetError naming the holder if another has it."""
    loc = os.fspath(location)
    if is_url(loc) or fcntl is None:
        yield
        return
    lock = lock_path(loc)
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
        fd = _acquire(lock, loc)
    except OSError as exc:
        if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            yield
            return
        raise
    try:
        try:
            os.ftruncate(fd, 0)
            os.write(fd, json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                     "since": time.strftime("%Y-%m-%dT%H:%M:%S%z")}).encode())
        except OSError:  # a full disk: the lock holds without its note
            pass
        yield
    finally:
        # Unlinked while still held: a writer that opens the name from now on makes a new file, and
        # one that opened this file before is told by the inode check in _acquire to start over.
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)


def _acquire(lock: Path, loc: str) -> int:
    """An open descriptor of ``lock`` holding its flock; SonarSetError while another holds it."""
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise SonarSetError(f"{loc}: another writer is at work on it ({holder}); "
                                "a store takes one writer at a time") from None
        try:
            if os.fstat(fd).st_ino == os.stat(lock).st_ino:
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)  # the holder before us removed this file as we locked it: lock the new one


def _holder(fd: int) -> str:
    try:
        doc = json.loads(os.pread(fd, 4096, 0) or b"{}")
        return f"pid {doc['pid']} on {doc['host']} since {doc['since']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "a process that has just started"
