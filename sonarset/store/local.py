"""What a local store directory may hold, checked before zarr opens anything in it (spec/FORMAT.md §2).

A store is a tree of directories and regular files. Anything else below its root is refused with
the path named: a FIFO blocks the reader that opens it, a device (``/dev/zero``) never ends, a
symbolic link may leave the store or loop back into it. Symbolic links are refused outright rather
than followed with care: a store is data to be copied, archived and served, and a link breaks in
each of those. Metadata documents (``zarr.json``) are capped in size and nesting depth, so that
no document can exhaust memory or the parser's stack.
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

from sonarset.errors import one_line
from sonarset.format.problems import Problem

#: The largest ``zarr.json`` a reader parses: far above any store's (a root with consolidated
#: metadata of 10,000 runs is ~20 MB), far below what would exhaust memory.
MAX_METADATA_BYTES = 64 * 2**20
#: Nesting a ``zarr.json`` may have: SonarSet's deepest is 6 (attributes.sonarset.processing...).
MAX_METADATA_DEPTH = 64

_KINDS = {stat.S_IFIFO: "a FIFO", stat.S_IFCHR: "a character device", stat.S_IFBLK: "a block device",
          stat.S_IFSOCK: "a socket", stat.S_IFLNK: "a symbolic link"}


def tree_problems(root: Path) -> list[Problem]:
    """Every entry below ``root`` that is not a directory or a regular file, and every metadata
    document that is too large, too deep or not JSON. Walks without following links."""
    problems: list[Problem] = []
    pending = [root]
    while pending:
        folder = pending.pop()
        try:
            entries = list(os.scandir(folder))
        except OSError as exc:
            problems.append(Problem(str(folder), f"cannot list the folder ({exc.strerror or one_line(exc)})"))
            continue
        for entry in entries:
            # the directory entry's type, no system call per file where the file system records it
            if entry.is_dir(follow_symlinks=False):
                pending.append(Path(entry.path))
            elif entry.is_file(follow_symlinks=False):
                if entry.name == "zarr.json" and folder != root:  # the root's is read by its own check
                    problems += document_problems(Path(entry.path))
            else:
                try:
                    kind = _KINDS.get(stat.S_IFMT(entry.stat(follow_symlinks=False).st_mode), "not a regular file")
                except OSError as exc:
                    problems.append(Problem(entry.path, f"cannot stat ({exc.strerror or one_line(exc)})"))
                    continue
                problems.append(Problem(entry.path, f"{kind}; a store holds only folders and regular files"))
    return sorted(problems, key=lambda p: p.where)


def read_document(path: Path, size: int | None = None):
    """A metadata document, parsed within the limits; ValueError with the reason otherwise."""
    size = path.stat().st_size if size is None else size
    if size > MAX_METADATA_BYTES:
        raise ValueError(f"{size / 2**20:.0f} MiB of metadata (the limit is {MAX_METADATA_BYTES // 2**20} MiB)")
    try:
        doc = json.loads(path.read_bytes())
    except RecursionError:
        raise ValueError("JSON nested too deeply to parse") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise _NotJSON(f"unreadable JSON ({one_line(exc)})") from None
    if json_depth(doc) > MAX_METADATA_DEPTH:
        raise ValueError(f"JSON nested deeper than {MAX_METADATA_DEPTH} levels")
    return doc


def document_problems(path: Path, size: int | None = None) -> list[Problem]:
    """A node's ``zarr.json`` beyond the limits. One that is merely not JSON, or not zarr metadata,
    is left to the node's own rules (``store.root``, ``store.run``), which name the node."""
    try:
        read_document(path, size)
    except _NotJSON:
        return []
    except ValueError as exc:
        return [Problem(str(path), str(exc))]
    except OSError as exc:
        return [Problem(str(path), f"unreadable ({exc.strerror or one_line(exc)})")]
    return []


class _NotJSON(ValueError):
    pass


def json_depth(doc) -> int:
    """How many objects and arrays deep a parsed JSON document nests (a scalar: 0), without recursion."""
    deepest, stack = 0, [(doc, 1)] if isinstance(doc, (dict, list)) else []
    while stack:
        node, depth = stack.pop()
        deepest = max(deepest, depth)
        children = node.values() if isinstance(node, dict) else node
        stack += [(c, depth + 1) for c in children if isinstance(c, (dict, list))]
    return deepest
