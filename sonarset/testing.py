"""Helpers for tests and benchmarks of remote stores: a read-only HTTP server on loopback."""

from __future__ import annotations

import contextlib
import functools
import http.server
import threading
from typing import Iterator


class CountingHandler(http.server.SimpleHTTPRequestHandler):
    """Serves files silently and counts GET requests (class attribute ``requests``)."""

    requests = 0

    def log_message(self, *args) -> None:
        pass

    def do_GET(self) -> None:
        type(self).requests += 1
        super().do_GET()


@contextlib.contextmanager
def serve_directory(directory: str) -> Iterator[tuple[str, type[CountingHandler]]]:
    """(base URL, handler class whose ``requests`` counts GETs) of ``directory`` served on 127.0.0.1."""
    handler = type("Handler", (CountingHandler,), {"requests": 0})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(handler, directory=directory))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", handler
    finally:
        server.shutdown()
        server.server_close()
