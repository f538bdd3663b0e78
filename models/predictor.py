"""The predictor protocol: all that the evaluation, the viewer, the experiments and the demo ask of a model.

A predictor maps a batch of windows, ``frames`` (B, n_in, R, A) float32 and ``commands``
(B, n_in + 1, 2), to the next frame (B, R, A). ``commands[:, -1]`` moves the robot from the last
input frame to the predicted one (docs/conventions.md, "Windows"). Anything with a ``name``, an
``n_in`` and such a ``predict`` is a predictor; the rest is optional:

- ``rollout(frames, commands, horizon) -> (B, horizon, R, A)`` with n_in + horizon commands, for a
  model that forecasts several steps at once; without one, ``predict`` is chained, each prediction
  fed back as the newest input frame;
- ``forecast_at(frames, commands, horizons) -> (B, len(horizons), R, A)``, ``horizons`` increasing
  steps, with n_in + horizons[-1] commands: the rollout's images at those steps only, for a model
  that forecasts each horizon directly from the measured frames and so need not compute the steps
  between (EchoWarp); the evaluation asks for its scored horizons. Without one, the rollout's steps
  are taken;
- ``card``: the model card of a trained model (a dict) or None. The evaluation compares its
  ``processing`` (absent: 'raw' images), ``rig`` and ``config.dt`` with the store's and notes a
  difference (models/echopt/cards.py);
- ``precision``: the arithmetic it computes in ("fp32", "bf16"), recorded beside the scores; None
  for a model that has no such choice;
- ``label``: how notes name it (a checkpoint: "echopt run-a/model"); by default its name;
- ``any_context``: it reads only the last frame, so it takes windows of any length and is fed those
  of the model beside it.

:class:`BasePredictor` gives those defaults. Every consumer takes a predictor through
:func:`as_predictor`, which checks the protocol once, in one line naming the predictor, and
returns a :class:`CheckedPredictor`: a view with every member declared, that checks each output's
shape. NumPy only: a package can implement a predictor without torch.
"""

from __future__ import annotations

import copy
import numbers
import warnings
from typing import Callable, Protocol, runtime_checkable

import numpy as np

from sonarset.errors import SonarSetError
from sonarset.windows import N_IN


@runtime_checkable
class Predictor(Protocol):
    name: str
    n_in: int  # input frames per window

    def predict(self, frames: np.ndarray, commands: np.ndarray) -> np.ndarray: ...


def chain_rollout(predict: Callable[[np.ndarray, np.ndarray], np.ndarray], frames: np.ndarray,
                  commands: np.ndarray, horizon: int) -> np.ndarray:
    """Predict ``horizon`` frames ahead with ``predict``, feeding each prediction back as the newest
    input frame.

    ``commands`` holds n_in + horizon commands (docs/conventions.md, "Windows"); step h uses
    commands h .. h + n_in. Returns (B, horizon, R, A): predictions for targets 1..horizon.
    """
    n_in = frames.shape[1]
    if commands.shape[1] < n_in + horizon:
        raise ValueError(f"need {n_in + horizon} commands for horizon {horizon}, got {commands.shape[1]}")
    # One buffer holds the measured inputs followed by the predictions; step h reads the view
    # buf[:, h:h + n_in], so after the first step the model's own predictions replace measured
    # frames, with no copying of windows.
    buf = np.empty((frames.shape[0], n_in + horizon, *frames.shape[2:]), dtype=np.float32)
    buf[:, :n_in] = frames
    for h in range(horizon):
        buf[:, n_in + h] = predict(buf[:, h:h + n_in], commands[:, h:h + n_in + 1])
    return buf[:, n_in:]


def checked_horizons(horizons) -> tuple[int, ...]:
    """``horizons`` as a tuple of increasing steps >= 1 (ValueError otherwise): what ``forecast_at``
    takes."""
    horizons = tuple(int(h) for h in horizons)
    if not horizons or list(horizons) != sorted(set(horizons)) or horizons[0] < 1:
        raise ValueError(f"horizons must be increasing steps >= 1, got {horizons}")
    return horizons


def rollout_steps(rollout: Callable[[np.ndarray, np.ndarray, int], np.ndarray], frames: np.ndarray,
                  commands: np.ndarray, horizons: tuple[int, ...]) -> np.ndarray:
    """(B, len(horizons), R, A): ``rollout``'s forecasts at ``horizons`` (increasing), for a model
    that cannot forecast them alone (or not that far ahead)."""
    return rollout(frames, commands, horizons[-1])[:, [h - 1 for h in horizons]]


def block_rollout(forecast: Callable[[np.ndarray, np.ndarray, int], np.ndarray], frames: np.ndarray,
                  commands: np.ndarray, horizon: int, block: int) -> np.ndarray:
    """``horizon`` frames ahead (B, horizon, R, A) from a model that forecasts up to ``block`` steps
    in one call, ``forecast(frames, commands, m) -> (B, m, R, A)`` with n_in + m commands: blocks
    of ``block`` steps, each block's context the previous block's last forecasts."""
    n_in = frames.shape[1]
    if commands.shape[1] < n_in + horizon:
        raise ValueError(f"need {n_in + horizon} commands for horizon {horizon}, got {commands.shape[1]}")
    buf = np.empty((frames.shape[0], n_in + horizon, *frames.shape[2:]), dtype=np.float32)
    buf[:, :n_in] = frames
    for h in range(0, horizon, block):
        m = min(block, horizon - h)
        buf[:, n_in + h:n_in + h + m] = forecast(buf[:, h:h + n_in], commands[:, h:h + n_in + m], m)
    return buf[:, n_in:]


def rollout(predictor: Predictor, frames: np.ndarray, commands: np.ndarray, horizon: int) -> np.ndarray:
    """``horizon`` frames ahead: the predictor's own ``rollout`` where it has one, else its
    ``predict`` chained (:func:`chain_rollout`)."""
    own = getattr(predictor, "rollout", None)  # optional in the protocol
    if callable(own):
        return own(frames, commands, horizon)
    return chain_rollout(predictor.predict, frames, commands, horizon)


class BasePredictor:
    """The optional members' defaults and a ``rollout`` that chains ``predict``. A subclass sets
    ``name`` (and ``n_in`` when its window is not the paper's 3 frames) and defines
    ``predict(frames, commands)``."""

    name: str
    n_in: int = N_IN
    card: dict | None = None
    precision: str | None = None
    any_context: bool = False

    @property
    def label(self) -> str:
        """The predictor's name until a label is set."""
        return self.__dict__.get("_label") or self.name

    @label.setter
    def label(self, value: str) -> None:
        self._label = value

    def rollout(self, frames: np.ndarray, commands: np.ndarray, horizon: int) -> np.ndarray:
        return chain_rollout(self.predict, frames, commands, horizon)


class CheckedPredictor:
    """A predictor as its consumers use it, checked by :func:`as_predictor`: every member of the
    protocol is here, optional ones at their defaults, and each output's shape is checked.

    ``name`` is the view's own: the evaluation renames one of two models of the same name here,
    not on the predictor. ``predictor`` is the object itself.
    """

    def __init__(self, predictor, who: str, *, name: str, n_in: int, card: dict | None, precision: str | None,
                 label: str, any_context: bool, own_rollout: Callable | None, own_forecast_at: Callable | None = None):
        self.predictor, self.who = predictor, who
        self.name, self.n_in, self.card, self.precision = name, n_in, card, precision
        self.label, self.any_context = label, any_context
        self._own_rollout, self._own_forecast_at = own_rollout, own_forecast_at

    def __repr__(self) -> str:
        return f"CheckedPredictor({self.name!r}, n_in={self.n_in}, of {self.who})"

    @property
    def chains(self) -> bool:
        """Its rollout feeds each prediction back as the newest input frame (it has no ``rollout``
        of its own): a forecast k steps ahead is then the next step from the k - 1 before it."""
        return self._own_rollout is None

    def predict(self, frames: np.ndarray, commands: np.ndarray) -> np.ndarray:
        out = self._call("predict", self.predictor.predict, frames, commands)
        return self._checked(out, (frames.shape[0], *frames.shape[2:]), "predict", "(B, R, A)")

    def rollout(self, frames: np.ndarray, commands: np.ndarray, horizon: int) -> np.ndarray:
        if self._own_rollout is None:  # chained through the checked predict
            return chain_rollout(self.predict, frames, commands, horizon)
        out = self._call("rollout", self._own_rollout, frames, commands, horizon)
        return self._checked(out, (frames.shape[0], horizon, *frames.shape[2:]), "rollout", "(B, horizon, R, A)")

    @property
    def forecasts_directly(self) -> bool:
        """It forecasts chosen horizons without the steps between (its own ``forecast_at``)."""
        return self._own_forecast_at is not None

    def forecast_at(self, frames: np.ndarray, commands: np.ndarray, horizons: tuple[int, ...]) -> np.ndarray:
        """(B, len(horizons), R, A): the forecasts ``horizons`` (increasing) steps ahead, by the
        predictor's own ``forecast_at``, else its rollout's steps."""
        horizons = tuple(horizons)
        if self._own_forecast_at is None:
            return rollout_steps(self.rollout, frames, commands, horizons)
        out = self._call("forecast_at", self._own_forecast_at, frames, commands, horizons)
        return self._checked(out, (frames.shape[0], len(horizons), *frames.shape[2:]), "forecast_at",
                             "(B, len(horizons), R, A)")

    def _call(self, what: str, method: Callable, *args):
        """``method(*args)``, each array a copy of its own: an evaluation hands every predictor the
        same windows, and one that wrote into its inputs would change what the models after it see.
        An error inside an outside predictor is that predictor's, so it is named in one line (our own
        errors, and interrupts, pass as they are)."""
        args = tuple(np.array(a) if isinstance(a, np.ndarray) else a for a in args)
        try:
            return method(*args)
        except (SonarSetError, KeyboardInterrupt, MemoryError):
            raise
        except Exception as exc:
            raise SonarSetError(f"predictor {self.who}: {what} raised {type(exc).__name__}: {exc}") from exc

    def _checked(self, out, shape: tuple[int, ...], what: str, layout: str) -> np.ndarray:
        got = getattr(out, "shape", None)
        if got is None or tuple(got) != shape:
            raise SonarSetError(f"predictor {self.who}: {what} returned "
                                f"{'shape ' + str(tuple(got)) if got is not None else type(out).__name__}, "
                                f"not {layout} = {shape}")
        kind = getattr(getattr(out, "dtype", None), "kind", None)  # numpy's; a tensor's dtype has none
        if kind is not None and kind not in "fiub":
            raise SonarSetError(f"predictor {self.who}: {what} returned {out.dtype} values, not real numbers")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", np.exceptions.ComplexWarning)
                return np.asarray(out, dtype=np.float32)
        except Exception as exc:
            raise SonarSetError(f"predictor {self.who}: {what} returned a {type(out).__name__} that is no "
                                f"float32 array ({type(exc).__name__}: {exc})") from exc


def _describe(obj) -> str:
    text = " ".join(repr(obj).split())
    return text if len(text) <= 60 else text[:57] + "..."


def as_predictor(obj, spec: str | None = None) -> CheckedPredictor:
    """``obj`` checked against the protocol, as a :class:`CheckedPredictor`; a SonarSetError in one
    line naming it (by ``spec``, else its repr) and every member that is missing or of the wrong
    kind. A view passed in comes back as a copy, so renaming it leaves the caller's as it was."""
    if isinstance(obj, CheckedPredictor):
        return copy.copy(obj)
    who = repr(spec) if spec else _describe(obj)
    if isinstance(obj, type):
        raise SonarSetError(f"predictor {who}: the class {obj.__name__}, not an instance of it")
    missing, problems = [], []
    name = getattr(obj, "name", None)
    if name is None:
        missing.append("name (a non-empty str)")
    elif not isinstance(name, str) or not name:
        problems.append(f"its name is {name!r}, not a non-empty str")
    n_in = getattr(obj, "n_in", None)
    if n_in is None:
        missing.append("n_in (input frames per window, an int >= 1)")
    elif isinstance(n_in, bool) or not isinstance(n_in, numbers.Integral) or n_in < 1:
        problems.append(f"its n_in is {n_in!r}, not an int >= 1")
    if not callable(getattr(obj, "predict", None)):
        missing.append("predict(frames, commands) method")
    if len(missing) == 3:
        kind = type(obj).__name__
        article = "an" if kind[:1].lower() in "aeiou" else "a"
        raise SonarSetError(f"predictor {who}: it is {article} {kind} object, not a predictor "
                            "(no name, n_in or predict(frames, commands))")
    method = getattr(obj, "rollout", None)
    if method is not None and not callable(method):
        problems.append("its rollout is not a method rollout(frames, commands, horizon)")
    forecast_at = getattr(obj, "forecast_at", None)
    if forecast_at is not None and not callable(forecast_at):
        problems.append("its forecast_at is not a method forecast_at(frames, commands, horizons)")
    card = getattr(obj, "card", None)
    if card is not None and not isinstance(card, dict):
        problems.append(f"its card is a {type(card).__name__}, not a dict or None")
    precision = getattr(obj, "precision", None)
    if precision is not None and (not isinstance(precision, str) or not precision):
        problems.append(f"its precision is {precision!r}, not a str (fp32, bf16) or None")
    label = getattr(obj, "label", None)
    if label is not None and label is not name and (not isinstance(label, str) or not label):  # a default label is the name
        problems.append(f"its label is {label!r}, not a non-empty str")
    any_context = getattr(obj, "any_context", False)
    if not isinstance(any_context, (bool, np.bool_)):
        problems.append(f"its any_context is {any_context!r}, not a bool")
    if missing or problems:
        raise SonarSetError(f"predictor {who}: " + "; ".join(
            ([f"has no {', no '.join(missing)}"] if missing else []) + problems))
    # BasePredictor's rollout chains predict: chained here instead, each step's output checked
    inherited = getattr(method, "__func__", None) is BasePredictor.rollout
    return CheckedPredictor(obj, who, name=name, n_in=int(n_in), card=card, precision=precision,
                            label=label or name, any_context=bool(any_context),
                            own_rollout=None if method is None or inherited else method, own_forecast_at=forecast_at)
