"""The names the models answer to, and the predictor a name stands for: one open table.

A model spec is resolved in this order:

1. a registered name, optionally ``NAME:ARG``:
   - the built-in baselines ``persistence``, ``naive``, ``flow`` (no ARG);
   - a checkpoint kind of :data:`CHECKPOINT_KINDS`: ``KIND:PATH`` (a run directory, a
     ``.safetensors`` checkpoint, an ``.onnx`` export), ``KIND:pretrained`` (the checkpoint the
     package ships, ``pretrained/KIND-*.safetensors``), a bare ``KIND`` meaning its pretrained one;
   - ``pretrained``: the recommended shipped model, that of :data:`RECOMMENDED_KIND`;
   - a plugin: an entry point of an installed package in the group ``sonarset.predictors``
     (name = ``package.module:factory``). A plugin never shadows a built-in name: the built-in
     wins and :func:`shadowed_plugins` says so (``sonarset models``, eval's notes);
2. ``package.module:factory``, or ``package.module:factory:ARG``, the module imported from
   ``sys.path`` and the working directory.

A factory (a plugin's or a module's) is called as ``factory(grid=SensorGrid, rig=RobotRig)``, plus
``arg=ARG`` when the spec was ``NAME:ARG`` or ``package.module:factory:ARG`` (a checkpoint of
one's own, say; a factory without an ``arg`` parameter refuses an ARG; none is passed without
one), plus ``device=`` and ``precision=`` where the factory has parameters of those names. What
it returns must answer the protocol (models/predictor.py); every spec comes back as a
:class:`~sonarset.models.predictor.CheckedPredictor`.

It imports neither torch nor SciPy (a predictor's modules are imported when one is made), so the
command line reads ``BASELINES`` and lists the names without loading a model.
"""

from __future__ import annotations

import importlib
import inspect
import json
import os
import re
import sys
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from typing import Callable

from sonarset.errors import SonarSetError
from sonarset.format.attrs import RobotRig, SensorGrid

from sonarset.models.predictor import CheckedPredictor, as_predictor
from sonarset.models.zoo import checkpoint_loader as zoo_checkpoint_loader

#: The paper's prediction horizons (1 = one-shot), eval's and the demo's default.
HORIZONS = (1, 3, 5, 10)
#: The entry-point group in which installed packages register predictors (name -> factory).
PLUGIN_GROUP = "sonarset.predictors"
PRETRAINED = "pretrained"
#: The checkpoint kind whose shipped model a bare ``pretrained`` names.
RECOMMENDED_KIND = "echowarp"
#: Where the shipped checkpoints live: ``KIND-*.safetensors`` with their cards beside them.
SHIPPED_DIR = Path(__file__).resolve().parent / "pretrained"


def _persistence(grid: SensorGrid, rig: RobotRig):
    from sonarset.models.baselines import Persistence

    return Persistence(grid)


def _naive(grid: SensorGrid, rig: RobotRig):
    from sonarset.models.baselines import NaiveShift

    return NaiveShift(grid, rig)


def _flow(grid: SensorGrid, rig: RobotRig):
    from sonarset.models.baselines import AcousticFlow

    return AcousticFlow(grid, rig)


#: name -> (factory(grid, rig), what it does). The baselines turn commands into image motion with
#: the rig (the robot that made the frames).
BUILT_INS: dict[str, tuple[Callable, str]] = {
    "persistence": (_persistence, "the last frame, unchanged: the floor every predictor must beat"),
    "naive": (_naive, "the last frame shifted by the commanded motion in range and azimuth"),
    "flow": (_flow, "the last frame warped along the commanded motion's acoustic flow (exact SE(2))"),
}
BASELINES = tuple(BUILT_INS)


def _load_echopt(arg: str, grid: SensorGrid, rig: RobotRig, device: str, precision: str):
    """EchoPT, the paper's transformer: a run directory, a .safetensors checkpoint or an .onnx export.

    It runs with the rig it was trained on (its config), in ``precision`` (models/echopt/precision.py:
    auto, fp32, bf16); an ONNX export runs in onnxruntime's fp32, without torch."""
    if arg.endswith(".onnx"):
        from sonarset.models.echopt.onnx_runtime import load_onnx_predictor

        return load_onnx_predictor(arg, grid)
    try:
        from sonarset.models.echopt.predictor import load_echopt_predictor
    except ImportError as exc:
        raise SonarSetError(f"model 'echopt:{arg}': EchoPT is not available in this installation ({exc})") from None
    return load_echopt_predictor(arg, grid, device=device, precision=precision)


#: KIND -> loader(arg, grid, rig, device, precision): the learned models that load from checkpoints.
CHECKPOINT_KINDS: dict[str, Callable] = {
    "echopt": _load_echopt,
    # the reference methods of video prediction (models/zoo/), trained by sonarset train --model KIND
    "convlstm": zoo_checkpoint_loader("convlstm"),
    "simvp": zoo_checkpoint_loader("simvp"),
    "echowarp": zoo_checkpoint_loader("echowarp"),
    "unet": zoo_checkpoint_loader("unet"),
}


@dataclass(frozen=True)
class RegistryEntry:
    name: str
    source: str  # "built-in", "shipped checkpoint", "plugin <distribution>"
    description: str


def _plugins() -> tuple[dict[str, EntryPoint], dict[str, str]]:
    """The installed plugins by name, and {name: note} for those a built-in name (or an earlier
    distribution's plugin) shadows."""
    found: dict[str, EntryPoint] = {}
    shadowed: dict[str, str] = {}
    for ep in entry_points(group=PLUGIN_GROUP):
        dist = _distribution(ep)
        if _built_in(ep.name):
            shadowed[ep.name] = (f"note: plugin {ep.name!r} of {dist} is shadowed by the built-in {ep.name!r}, "
                                 f"which is used; its factory is {ep.value}")
        elif ep.name in found:
            shadowed[ep.name] = (f"note: plugin {ep.name!r} of {dist} is shadowed by that of "
                                 f"{_distribution(found[ep.name])}, which is used")
        else:
            found[ep.name] = ep
    return found, shadowed


def _distribution(ep: EntryPoint) -> str:
    return ep.dist.metadata["Name"] if ep.dist is not None else "an unknown distribution"


def _built_in(name: str) -> bool:
    return name in BUILT_INS or name in CHECKPOINT_KINDS or name == PRETRAINED


def shadowed_plugins() -> dict[str, str]:
    """{plugin name: a note saying which name wins} for the installed plugins that are not used."""
    return _plugins()[1]


def shipped_checkpoint(kind: str) -> Path | None:
    """The checkpoint the package ships for ``kind`` (``pretrained/KIND-*.safetensors``), if any."""
    return next(iter(sorted(SHIPPED_DIR.glob(f"{kind}-*.safetensors"))), None)


def _shipped_description(path: Path) -> str:
    try:
        card = json.loads(path.with_suffix(".json").read_text())
        return f"{path.stem}: preset {card['preset']}, {card['n_params'] / 1e6:.2f} M parameters"
    except (OSError, ValueError, KeyError, TypeError):
        return path.stem


def available_predictors() -> list[RegistryEntry]:
    """Every name this installation knows, where it comes from and what it is: the built-ins, the
    shipped checkpoints, each checkpoint kind's ``KIND:PATH``, and the plugins."""
    entries = [RegistryEntry(name, "built-in", text) for name, (_, text) in BUILT_INS.items()]
    recommended = shipped_checkpoint(RECOMMENDED_KIND)
    if recommended is not None:
        entries.append(RegistryEntry(PRETRAINED, "shipped checkpoint",
                                     f"the recommended shipped model, {RECOMMENDED_KIND}:{PRETRAINED}"))
    for kind, loader in CHECKPOINT_KINDS.items():
        shipped = shipped_checkpoint(kind)
        if shipped is not None:
            entries.append(RegistryEntry(f"{kind}:{PRETRAINED}", "shipped checkpoint", _shipped_description(shipped)))
        summary = (loader.__doc__ or kind).strip().splitlines()[0].rstrip(".")
        entries.append(RegistryEntry(f"{kind}:PATH", "built-in", summary))
    plugins, _ = _plugins()
    entries += [RegistryEntry(name, f"plugin {_distribution(ep)}", ep.value) for name, ep in plugins.items()]
    return entries


def known_names() -> list[str]:
    return [e.name for e in available_predictors()]


_MODULE = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*")


def _factory_part(text: str) -> bool:
    """Whether ``text``, after a module's name and ':', is ``factory`` or ``factory:ARG``."""
    attribute, with_arg, arg = text.partition(":")
    return bool(_MODULE.fullmatch(attribute)) and (not with_arg or bool(arg))


def make_predictor(spec: str, grid: SensorGrid, rig: RobotRig, *, device: str = "cpu",
                   precision: str = "auto") -> CheckedPredictor:
    """The predictor ``spec`` names (see the module's docstring for the order), on ``grid`` for a
    robot ``rig`` (the one that made the frames), checked against the protocol."""
    spec = spec.strip()
    name, sep, arg = spec.partition(":")
    if name in BUILT_INS or name == PRETRAINED:
        if sep:
            raise SonarSetError(f"model {spec!r}: {name} takes nothing after ':'", parameter="model_specs")
        obj = (BUILT_INS[name][0](grid, rig) if name in BUILT_INS
               else CHECKPOINT_KINDS[RECOMMENDED_KIND](PRETRAINED, grid, rig, device, precision))
    elif name in CHECKPOINT_KINDS:
        obj = CHECKPOINT_KINDS[name](arg or PRETRAINED, grid, rig, device, precision)
    else:
        plugins, _ = _plugins()
        if spec in plugins or name in plugins:
            ep = plugins[spec] if spec in plugins else plugins[name]
            try:
                factory = ep.load()
            except Exception as exc:  # the plugin's own import: any error
                raise SonarSetError(f"predictor {spec!r}: plugin {ep.name!r} of {_distribution(ep)} does not load "
                                    f"({ep.value}: {_one_line(exc)})") from exc
            obj = _call_factory(factory, spec, ep.value, None if spec in plugins else arg, grid, rig, device, precision)
        elif sep and _MODULE.fullmatch(name) and _factory_part(arg):
            attribute, with_arg, factory_arg = arg.partition(":")
            obj = _call_factory(_import_factory(spec, name, attribute), spec, f"{name}:{attribute}",
                                factory_arg if with_arg else None, grid, rig, device, precision)
        else:
            raise SonarSetError(f"unknown model {spec!r}: {_known_hint()}", parameter="model_specs")
    return as_predictor(obj, spec)


def _known_hint() -> str:
    return (f"the known names are {', '.join(known_names())} (sonarset models lists them); name any other "
            f"predictor as package.module:factory[:ARG], or install a package that registers it in the entry-point "
            f"group {PLUGIN_GROUP!r}")


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0]}" if text else type(exc).__name__


def _import_factory(spec: str, module_name: str, attribute: str) -> Callable:
    """``module_name``'s ``attribute`` (dotted), imported as ``python -m`` would: the working
    directory first on the path, for a predictor written beside the data (after the installed
    packages, a user's ``test.py`` was the standard library's ``test``)."""
    if os.getcwd() not in sys.path and "" not in sys.path:
        sys.path.insert(0, os.getcwd())
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name is not None and (module_name == exc.name or module_name.startswith(exc.name + ".")):
            raise SonarSetError(f"unknown model {spec!r}: no module {module_name!r} to import; "
                                f"{_known_hint()}", parameter="model_specs") from None
        raise SonarSetError(f"predictor {spec!r}: module {module_name!r} does not import ({_one_line(exc)})") from exc
    except Exception as exc:  # the module's own code: any error
        raise SonarSetError(f"predictor {spec!r}: module {module_name!r} does not import ({_one_line(exc)})") from exc
    target = module
    for part in attribute.split("."):
        if not hasattr(target, part):
            where = getattr(module, "__file__", None)
            raise SonarSetError(f"predictor {spec!r}: module {module_name!r}{f' ({where})' if where else ''} "
                                f"has no attribute {attribute!r}")
        target = getattr(target, part)
    if not callable(target):
        raise SonarSetError(f"predictor {spec!r}: {module_name}.{attribute} is a {type(target).__name__}, not a "
                            "factory(grid, rig) that returns a predictor")
    return target


def _call_factory(factory: Callable, spec: str, where: str, arg: str | None, grid: SensorGrid, rig: RobotRig,
                  device: str, precision: str):
    """``factory(grid=, rig=)`` with ``arg``, ``device`` and ``precision`` where it takes them; one
    line naming the spec when it raises."""
    try:
        params = inspect.signature(factory).parameters
    except (TypeError, ValueError):  # a callable without a signature: the protocol's arguments only
        params = {}
    kwargs: dict = {"grid": grid, "rig": rig}
    kwargs.update({k: v for k, v in (("device", device), ("precision", precision)) if k in params})
    if arg is not None:
        if "arg" not in params:
            raise SonarSetError(f"predictor {spec!r}: its factory {where} takes nothing after ':' (no 'arg' parameter)")
        kwargs["arg"] = arg
    try:
        obj = factory(**kwargs)
    except SonarSetError:
        raise
    except Exception as exc:  # the factory's own code: any error
        raise SonarSetError(f"predictor {spec!r}: its factory {where} raised {_one_line(exc)}") from exc
    except SystemExit as exc:  # a script's habit: not the command's exit
        raise SonarSetError(f"predictor {spec!r}: its factory {where} called sys.exit({exc.code!r})") from None
    if obj is None:
        raise SonarSetError(f"predictor {spec!r}: its factory {where} returned None, not a predictor")
    return obj


def model_option_spec(text: str) -> str:
    """The spec a command's ``model`` value means: a name, ``KIND:ARG`` or ``module:factory`` as it is; a
    path (it has a separator, a checkpoint's suffix, or exists) as an EchoPT checkpoint's, which is
    all the option took before."""
    text = text.strip()
    name, sep, arg = text.partition(":")
    if _built_in(name) or name in _plugins()[0]:
        return text
    if sep and _MODULE.fullmatch(name) and _factory_part(arg) and not Path(text).exists():
        return text
    if "/" in text or os.sep in text or text.endswith((".safetensors", ".onnx", ".json")) or Path(text).exists():
        return f"echopt:{text}"
    return text
