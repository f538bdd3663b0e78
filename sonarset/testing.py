"""Helpers for tests and benchmarks: a read-only HTTP server on loopback, which can also misbehave
the ways real servers do (``FAULTS``), and a look at the process table (Linux ``/proc``)."""

from __future__ import annotations

import contextlib
import functools
import http.server
import threading
import time
from pathlib import Path
from typing import Iterator


class CountingHandler(http.server.SimpleHTTPRequestHandler):
    """Serves files silently and counts GET requests (class attribute ``requests``)."""

    requests = 0

    def log_message(self, *args) -> None:
        pass

    fault: str | None = None
    faults_left = -1  # how many requests still fail (-1: all)

    def do_GET(self) -> None:
        cls = type(self)
        cls.requests += 1
        faulty = cls.fault is not None and cls.faults_left != 0 and (cls.fault in ("hang", "trickle") or "/c/" in self.path)
        if faulty:
            cls.faults_left -= 1
        try:
            return FAULTS[cls.fault](self) if faulty else super().do_GET()
        except (BrokenPipeError, ConnectionResetError):  # the client gave up first (its timeout): as it should
            return None

    def _hang(self) -> None:
        time.sleep(60)

    def _trickle(self) -> None:
        self.send_response(200)
        self.send_header("Content-Length", "100")
        self.end_headers()
        for _ in range(100):
            self.wfile.write(b"{")
            self.wfile.flush()
            time.sleep(1)

    def _server_error(self) -> None:
        self.send_error(500)

    def _short_body(self) -> None:
        data = open(self.translate_path(self.path), "rb").read()
        self.send_response(200)
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data[: len(data) // 2])
        self.close_connection = True


# What a misbehaving server does: accept and never answer, answer a byte a second (both for every
# request), or for chunk requests only: answer HTTP 500, or send half the body it announced.
FAULTS = {"hang": CountingHandler._hang, "trickle": CountingHandler._trickle,
          "server_error": CountingHandler._server_error, "short_body": CountingHandler._short_body}


@contextlib.contextmanager
def serve_directory(directory: str, fault: str | None = None,
                    times: int = -1) -> Iterator[tuple[str, type[CountingHandler]]]:
    """(base URL, handler class whose ``requests`` counts GETs) of ``directory`` served on 127.0.0.1;
    with a ``fault`` (a key of ``FAULTS``) the first ``times`` affected requests (-1: all) misbehave."""
    if fault is not None and fault not in FAULTS:
        raise ValueError(f"fault must be one of {sorted(FAULTS)}, got {fault!r}")
    handler = type("Handler", (CountingHandler,), {"requests": 0, "fault": fault, "faults_left": times})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(handler, directory=directory))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    # a hanging request must not hold the caller at shutdown
    server.daemon_threads, server.block_on_close = True, False
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", handler
    finally:
        server.shutdown()
        server.server_close()


def child_pids(pid: int) -> set[int]:
    """The processes whose parent is ``pid``."""
    out = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                out.add(int(stat.parent.name))
        except (OSError, ValueError, IndexError):
            pass
    return out


def pool_workers(pid: int) -> set[int]:
    """The children of ``pid`` that multiprocessing spawned (its resource tracker is a child too)."""
    found = set()
    for child in child_pids(pid):
        try:
            if b"spawn_main" in Path(f"/proc/{child}/cmdline").read_bytes():
                found.add(child)
        except OSError:
            pass
    return found


def running(pid: int) -> bool:
    """Whether ``pid`` is alive (a zombie is not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def strip_checksums(location: str | Path, version: str | None = None) -> None:
    """The store at ``location`` as a writer before format 1.2 made it: every run array rewritten
    without the crc32c codec, and with ``version``, ``format_version`` set to it (the conformance
    fixtures of older versions, and the tests and benches of reading them)."""
    import zarr
    from zarr.codecs import Crc32cCodec

    root = zarr.open_group(str(location), mode="r+", use_consolidated=False)
    for _, run in root.groups():
        for name, old in list(run.arrays()):
            values, attrs = old[...], dict(old.attrs)
            compressors = tuple(c for c in old.compressors if not isinstance(c, Crc32cCodec)) or None
            chunks, dims, fill = old.chunks, old.metadata.dimension_names, old.metadata.fill_value
            del run[name]
            run.create_array(name, shape=values.shape, dtype=values.dtype, chunks=chunks, dimension_names=dims,
                             compressors=compressors, fill_value=fill, attributes=attrs)[...] = values
    if version is not None:
        root.attrs["sonarset"] = {**root.attrs["sonarset"], "format_version": version}
    zarr.consolidate_metadata(str(location))
