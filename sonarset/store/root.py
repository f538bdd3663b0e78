"""The root group of a store: where it is, its attributes, its run groups, their attributes, and
its consolidated metadata (spec/FORMAT.md §2-§6).

Everything here applies the rules of ``sonarset.format.rules`` to what is stored, and returns the
Problems it finds located at their node: the readers raise the first (``raise_first``),
``validate`` lists them all. ``StoreRoot`` is what a run and a run writer need of a store; the
facade (``sonarset.store.store.SonarStore``) builds on it.
"""

from __future__ import annotations

import errno
import json

import warnings
from pathlib import Path
from typing import Any, Iterable

import zarr

from sonarset.errors import FormatError, RemoteError, SonarSetError, one_line
from sonarset.format.attrs import NAMESPACE, Processing, RobotRig, RunAttrs, SensorGrid, StoreAttrs, run_name_problems
from sonarset.format.problems import Problem, raise_first
from sonarset.format.rules import parse_run_attrs, parse_store_attrs, root_document_problems
from sonarset.store.local import read_document, tree_problems
from sonarset.store.zarrio import child_names, first_unreadable_node, is_url, open_group, remote_store

# Listing a group while another process writes into it atomically shows that writer's temp file
# ("zarr.<id>.partial"); it is not a node, zarr skips it, and the warning is noise.
# Other strays (a junk folder, a killed writer's leftovers) are not nodes either: readers ignore
# them, as the spec says of anything that is not a node.
warnings.filterwarnings("ignore", message=r"Object at .* is not recognized", category=UserWarning)
# zarr-python warns on every consolidation that consolidated metadata is not yet in the v3 spec;
# the spec (FORMAT.md §6) makes it optional and advisory, so the warning is noise to our users.
warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part")


def local_root_problems(path: Path) -> list[Problem]:
    """What keeps a local directory from being a store's root, before zarr is asked to open it."""
    where = str(path)
    if not path.exists():
        return [Problem(where, "no such file or directory")]
    if not path.is_dir():
        return [Problem(where, "not a zarr store (a file, not a directory)")]
    meta = path / "zarr.json"
    if not meta.is_file():
        if (path / ".zgroup").exists() or (path / ".zarray").exists():
            return [Problem(where, "a Zarr v2 store; SonarSet requires Zarr v3")]
        return [Problem(where, "not a zarr store (no zarr.json at its root)")]
    try:  # zarr's own message would not say which file
        doc = read_document(meta)
    except ValueError as exc:
        return [Problem(str(meta), str(exc))]
    except OSError as exc:
        return [Problem(str(meta), f"unreadable JSON ({one_line(exc)})")]
    return [p.at(where) for p in root_document_problems(doc)] or tree_problems(path)


def store_attrs(group: zarr.Group, location: str) -> tuple[StoreAttrs | None, list[Problem]]:
    """The root's attributes, or None and every problem with them."""
    attrs, problems = parse_store_attrs(group.attrs.get(NAMESPACE))
    return attrs, [p.at(location) for p in problems]


def read_store_attrs(group: zarr.Group, location: str) -> StoreAttrs:
    """The root's attributes; FormatError naming the first problem."""
    attrs, problems = store_attrs(group, location)
    raise_first(problems)
    return attrs


def child_groups(group: zarr.Group, location: str) -> tuple[dict[str, zarr.Group], list[Problem]]:
    """The root's child groups by name, sorted, opened by one listing (zarr parses each child's
    metadata as it lists), and a problem for each child whose metadata zarr cannot parse (one
    broken ``zarr.json`` makes the whole listing fail: then each child is opened on its own)."""
    try:
        return dict(sorted(group.groups())), []
    except RemoteError:  # the server failed, not the store: never a finding
        raise
    except Exception:
        pass
    nodes, problems = {}, []
    for name in child_names(group):
        try:
            node = group[name]
        except RemoteError:
            raise
        except Exception as exc:
            problems.append(Problem(f"{location}/{name}", f"unreadable zarr metadata ({one_line(exc)})"))
            continue
        if isinstance(node, zarr.Group):
            nodes[name] = node
    return nodes, problems


def run_tree(group: zarr.Group) -> dict[str, tuple[zarr.Group, dict[str, zarr.Array]]] | None:
    """{name: (group, {array name: array})} of the root's child groups, sorted, from one listing of
    two levels: what a reader about to open every run needs, without a listing per run. None where
    a node's metadata is unreadable (it fails the whole listing: open them one by one then)."""
    try:
        listed = dict(group.members(max_depth=1))
    except RemoteError:
        raise
    except Exception:
        return None
    tree = {k: (v, {}) for k, v in sorted(listed.items()) if "/" not in k and isinstance(v, zarr.Group)}
    for key, node in sorted(listed.items()):
        parent, _, child = key.partition("/")
        if child and parent in tree and isinstance(node, zarr.Array):
            tree[parent][1][child] = node
    return tree


def run_groups(group: zarr.Group, location: str) -> tuple[list[str], list[Problem]]:
    """The names of the root's child groups, sorted, and the problems of ``child_groups``."""
    nodes, problems = child_groups(group, location)
    return list(nodes), problems


def run_group_attrs(group: zarr.Group, location: str, name: str,
                    node: zarr.Group | None = None) -> tuple[RunAttrs | None, list[Problem]]:
    """Run group ``name``'s attributes, or None and every problem with the group: its name, its
    metadata and its attributes. ``node`` is the group where it is already open (a listing opens
    every child): then nothing is read again."""
    where = f"{location}/{name}"
    problems = [p.at(where) for p in run_name_problems(name)]
    try:
        raw = (group[name] if node is None else node).attrs.get(NAMESPACE)
    except RemoteError:
        raise
    except Exception as exc:
        return None, problems + [Problem(where, f"unreadable zarr metadata ({one_line(exc)})")]
    attrs, found = parse_run_attrs(raw)
    return attrs, problems + [p.at(where) for p in found]


class StoreRoot:
    """A store's root group and attributes: what runs and run writers need of a store."""

    def __init__(self, group: zarr.Group, location: str, mode: str):
        self.group = group
        self.location = location
        self.mode = mode
        self.attrs = read_store_attrs(group, location)

    @property
    def grid(self) -> SensorGrid:
        return self.attrs.grid

    @property
    def format_version(self) -> str:
        return self.attrs.format_version

    @property
    def processing(self) -> Processing:
        """How the images were made (format 1.1; a 1.0 store's images are 'raw')."""
        return self.attrs.processing

    @property
    def rig(self) -> RobotRig | None:
        """The robot geometry: the store's ``rig`` attribute (1.1), else None when unknown.

        Backward compatibility: a store without ``rig`` (format 1.0) whose complete runs were all
        made by the simulator gets the rig recorded in their provenance
        (:meth:`RobotRig.from_provenance`). This is the one place that reads geometry from the
        free-form ``source``.
        """
        if self.attrs.rig is not None:
            return self.attrs.rig
        if self.mode == "r":  # a reader's view does not change: read every run's provenance once
            if not hasattr(self, "_provenance_rig"):
                self._provenance_rig = self._rig_from_provenance()
            return self._provenance_rig
        return self._rig_from_provenance()

    def _rig_from_provenance(self) -> RobotRig | None:
        rigs = set()
        for attrs in self.listed_runs().values():
            src = attrs.source
            rig = RobotRig.from_provenance(src) if src.get("kind") == "simulator" else None
            if rig is None:
                return None
            rigs.add(rig)
        return rigs.pop() if len(rigs) == 1 else None

    def run_attrs(self, name: str) -> RunAttrs | None:
        """Run ``name``'s attributes; None when its metadata or attributes are unusable."""
        try:
            raw = self.group[name].attrs.get(NAMESPACE)
        except RemoteError:
            raise
        except Exception:  # unparseable metadata: not a usable run
            return None
        return parse_run_attrs(raw)[0]

    def run_groups(self) -> dict[str, zarr.Group]:
        """The root's child groups by name, sorted, from one listing. A reader refuses a store
        with a child whose metadata zarr cannot parse, naming it; a writer (``r+``) skips it, so
        that it can still replace or add runs."""
        nodes, problems = child_groups(self.group, self.location)
        if self.mode == "r":
            raise_first(problems)
        return nodes

    def group_names(self) -> list[str]:
        """The names of ``run_groups``."""
        return list(self.run_groups())

    def child_group(self, name: str) -> zarr.Group | None:
        """The root's child group ``name``, opened alone (looking one run up by listing them all
        would make opening every run cost the square of the runs); None when there is none.
        FormatError when its metadata is unreadable."""
        if name in ("", ".", "..") or "/" in name:  # not a child's name: a path
            return None
        try:
            node = self.group[name]
        except KeyError:
            return None
        except RemoteError:
            raise
        except Exception as exc:
            raise FormatError(f"{self.location}/{name}: unreadable zarr metadata ({one_line(exc)})") from None
        return node if isinstance(node, zarr.Group) else None

    def listed_runs(self, include_incomplete: bool = False) -> dict[str, RunAttrs]:
        """{name: attributes} of the runs (complete ones unless asked), sorted, from one listing;
        groups whose attributes are unusable are left out."""
        out = {}
        for name, node in self.run_groups().items():
            attrs = parse_run_attrs(node.attrs.get(NAMESPACE))[0]
            if attrs is not None and (attrs.complete or include_incomplete):
                out[name] = attrs
        return out

    def runs(self, split: str | None = None, include_incomplete: bool = False,
             worlds: Iterable[str] | None = None) -> list[str]:
        """Names of the runs (complete ones unless asked), sorted, optionally of one split and of
        the world families (or world files) ``worlds`` that their ``source.world`` names."""
        wanted = None if worlds is None else set(worlds)
        return [name for name, attrs in self.listed_runs(include_incomplete).items()
                if (split is None or attrs.split == split)
                and (wanted is None or (attrs.source or {}).get("world") in wanted)]

    # ---- writing --------------------------------------------------------------------------
    def require_writable(self) -> None:
        if self.mode == "r":
            raise SonarSetError(f"{self.location}: store is open read-only")

    def delete_run(self, name: str) -> None:
        self.require_writable()
        if name in self.group.group_keys():
            del self.group[name]

    def consolidate(self) -> None:
        """Rewrite the root's consolidated metadata; call after runs were written elsewhere."""
        self.require_writable()
        consolidate(self.group, self.location)


def consolidate(group: zarr.Group, location: str) -> None:
    """Rewrite the consolidated metadata of the root ``group``; FormatError naming a node whose
    metadata zarr cannot parse (zarr parses every node's, so one broken node stops it)."""
    try:
        zarr.consolidate_metadata(group.store)
    except OSError as exc:
        # A read-only store whose snapshot is current needs no write: nothing to do is success.
        if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM) and \
                consolidated_staleness(group, child_names(group)) is None:
            return
        raise
    except RemoteError:
        raise
    except Exception as exc:
        where = first_unreadable_node(group)
        raise FormatError(f"{location}{'/' + where[0] if where else ''}: unreadable zarr metadata "
                          f"({one_line(where[1] if where else exc)}); cannot consolidate") from None



def consolidated_staleness(root: zarr.Group, names: list[str]) -> str | None:
    """How the root's consolidated metadata disagrees with the run groups ``names`` and their arrays
    as stored ("stale (it lacks run_003 ...)"), or None when it agrees or there is none."""
    from zarr.core.buffer import default_buffer_prototype
    from zarr.core.sync import sync

    raw = sync(root.store.get(f"{root.path}/zarr.json" if root.path else "zarr.json", prototype=default_buffer_prototype()))
    doc = json.loads(raw.to_bytes()) if raw is not None else None
    if not isinstance(doc, dict) or doc.get("consolidated_metadata") is None:
        return None
    try:
        cons = zarr.open_group(root.store, mode="r", use_consolidated=True)
        listed = cons.metadata.consolidated_metadata.flattened_metadata
    except Exception as exc:
        return f"unreadable ({one_line(exc)})"
    actual, unreadable = node_metadata(root, names)
    # Compare runs and their arrays; what cannot be read is reported by the run checks already.
    listed = {k: v for k, v in listed.items()
              if k.count("/") <= 1 and k not in unreadable and k.split("/")[0] not in unreadable}

    def plain(meta) -> dict:
        d = meta.to_dict()
        d.pop("consolidated_metadata", None)  # nested snapshots are compared node by node
        return d

    lacks = sorted(set(actual) - set(listed))
    extra = sorted(set(listed) - set(actual))
    differ = sorted(k for k in set(actual) & set(listed) if plain(actual[k]) != plain(listed[k]))
    if not (lacks or extra or differ):
        return None
    if lacks:
        detail = f"it lacks {lacks[0]}" + (f" and {len(lacks) - 1} more node(s)" if len(lacks) > 1 else "")
    elif extra:
        detail = f"it lists {extra[0]}, which the store does not hold"
    else:
        detail = f"its copy of {differ[0]}'s metadata differs from the store's"
    return f"stale ({detail}; readers of URLs trust it)"


def node_metadata(root: zarr.Group, names: list[str]) -> tuple[dict, set[str]]:
    """The metadata of every readable node under the root's run groups (runs and their arrays),
    and the keys of those whose metadata zarr cannot parse (the run checks report them)."""
    try:  # one listing of the runs and their arrays, where every node's metadata parses
        listed = dict(root.members(max_depth=1))
    except RemoteError:
        raise
    except Exception:  # a node zarr cannot parse fails the whole listing: then node by node, below
        listed = None
    if listed is not None:
        wanted = set(names)
        return ({k: v.metadata for k, v in listed.items() if k.split("/")[0] in wanted},
                {k for k in listed if "/" not in k and k not in wanted})  # children that are no group
    actual, unreadable = {}, set()
    for name in names:
        try:
            group = root[name]
            actual[name] = group.metadata
        except RemoteError:
            raise
        except Exception:
            unreadable.add(name)
            continue
        for child in child_names(group):
            key = f"{name}/{child}"
            try:
                actual[key] = root[key].metadata
            except RemoteError:
                raise
            except Exception:
                unreadable.add(key)
    unreadable |= {n for n in child_names(root) if n not in names}  # children that are no group
    return actual, unreadable

def open_root(location: str, mode: str = "r", *, storage_options: dict | None = None,
              consolidated: bool | None = None, cache_bytes: int | None = None,
              remote_limits=None, root_checked: bool = False) -> tuple[zarr.Group, str]:
    """The root group at ``location`` (a local path or an fsspec URL) and the location as the
    store names it, opened as ``open_store`` says; FormatError when it is not a zarr v3 group.
    ``root_checked``: the caller found no ``local_root_problems`` already (they walk the tree)."""
    loc = location
    if not is_url(loc):
        path = Path(loc.removeprefix("file://"))
        if not root_checked:
            raise_first(local_root_problems(path))
        loc = str(path)
        if consolidated is None:
            consolidated = False
    target: Any = loc
    if is_url(loc):
        target = remote_store(loc, storage_options, read_only=mode == "r", cache_bytes=cache_bytes,
                              limits=remote_limits)
        storage_options = None
    try:
        return open_group(target, mode, storage_options, consolidated), loc
    except (FileNotFoundError, KeyError, zarr.errors.GroupNotFoundError) as exc:
        raise FormatError(f"{loc}: not a zarr store ({type(exc).__name__})") from None
    except (OSError, SonarSetError):
        raise
    except RemoteError:
        raise
    except Exception as exc:  # zarr's metadata errors are ValueError, TypeError, its own classes...
        raise FormatError(f"{loc}: cannot open as a zarr v3 group: {one_line(exc)}") from None
