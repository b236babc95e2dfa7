"""Named, documented, validated components: the stage registry.

A stage is a function registered under a ``(kind, name)`` pair together with a frozen
dataclass of parameters. Each parameter field is declared with :func:`param`, which records
its default, one-line help, unit and range or choices; ``stereocli stages`` prints them and
:func:`Stage.make_params` validates user values against them.

Example
-------
>>> from dataclasses import dataclass
>>> @dataclass(frozen=True)
... class BoxParams:
...     radius: int = param(3, "half window size", unit="px", low=0, high=50)
>>> @register("aggregation", "box_example", BoxParams)
... def box(state, p):
...     '''Box filter (doctest example).'''
>>> get("aggregation", "box_example").make_params({"radius": 2}, source="x.yaml").radius
2
>>> _unregister("aggregation", "box_example")
"""

from __future__ import annotations

import dataclasses
import difflib
import fnmatch
import typing
from dataclasses import dataclass, field
from typing import Any, Callable

from .errors import ConfigError

#: Pipeline order of the stage kinds.
KINDS = ("preprocess", "cost", "aggregation", "optimizer", "refinement")


def param(
    default: Any,
    help: str,
    *,
    unit: str = "",
    low: float | None = None,
    high: float | None = None,
    choices: tuple | None = None,
) -> Any:
    """Declare a stage parameter as a dataclass field with its documentation and bounds.

    ``low``/``high`` are inclusive bounds for numbers (and for each element of int pairs).
    """
    meta = {"help": help, "unit": unit, "low": low, "high": high, "choices": choices}
    if isinstance(default, (list, dict)):
        raise TypeError("use tuples for sequence defaults (dataclass fields must be immutable)")
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class ParamSpec:
    """What ``stereocli stages`` prints about one parameter."""

    name: str
    type_name: str
    default: Any
    help: str
    unit: str
    low: float | None
    high: float | None
    choices: tuple | None

    def describe_range(self) -> str:
        if self.choices:
            return "{" + ", ".join(map(str, self.choices)) + "}"
        if self.low is not None or self.high is not None:
            lo = "-inf" if self.low is None else f"{self.low:g}"
            hi = "inf" if self.high is None else f"{self.high:g}"
            return f"[{lo}, {hi}]"
        return ""


@dataclass(frozen=True)
class Stage:
    """A registered stage.

    ``func(state, params)`` runs the stage on a :class:`stereocli.match.state.MatchState`.
    ``needs_cost`` marks refinement stages that read the cost volume (they run inside each row
    strip, before the volume is dropped); ``needs_right`` marks stages that need the right-view
    disparity (the pipeline computes it from the final cost volume when the optimizer did not);
    ``fills_holes`` marks stages that fill invalid pixels (``match --keep-invalid`` skips them).
    """

    kind: str
    name: str
    func: Callable
    params_cls: type
    summary: str
    doc: str
    needs_cost: bool = False
    needs_right: bool = False
    fills_holes: bool = False

    def param_specs(self) -> list[ParamSpec]:
        hints = typing.get_type_hints(self.params_cls)
        specs = []
        for f in dataclasses.fields(self.params_cls):
            m = f.metadata
            specs.append(
                ParamSpec(
                    name=f.name,
                    type_name=_type_name(hints[f.name]),
                    default=f.default,
                    help=m.get("help", ""),
                    unit=m.get("unit", ""),
                    low=m.get("low"),
                    high=m.get("high"),
                    choices=m.get("choices"),
                )
            )
        return specs

    def make_params(self, values: dict[str, Any], *, source: str = "<config>", section: str = ""):
        """Validate ``values`` (a mapping from the config) and build the frozen params object.

        Raises :class:`ConfigError` naming ``source``, the key, and valid choices / close
        matches on an unknown key, a wrong type or an out-of-range value.
        """
        hints = typing.get_type_hints(self.params_cls)
        names = [f.name for f in dataclasses.fields(self.params_cls)]
        where = f"{source}: {section + '.' if section else ''}"
        kwargs = {}
        for key, value in values.items():
            if key == "name":
                continue
            if key not in names:
                raise ConfigError(
                    f"{where}{key}: unknown parameter of {self.kind} stage '{self.name}'"
                    + _suggest(key, names)
                )
            kwargs[key] = _coerce(value, hints[key], f"{where}{key}", self._meta(key))
        return self.params_cls(**kwargs)

    def _meta(self, key: str) -> dict:
        return next(f.metadata for f in dataclasses.fields(self.params_cls) if f.name == key)


def _type_name(tp: Any) -> str:
    if typing.get_origin(tp) is tuple:
        return "pair of " + _type_name(typing.get_args(tp)[0])
    return getattr(tp, "__name__", str(tp))


def _suggest(word: str, options: list[str]) -> str:
    close = difflib.get_close_matches(word, options, n=3, cutoff=0.5)
    text = f"; valid: {', '.join(sorted(options))}" if options else "; it takes no parameters"
    if close:
        text = f"; did you mean {' or '.join(repr(c) for c in close)}?" + text
    return text


def _coerce(value: Any, tp: Any, where: str, meta: dict) -> Any:
    """Check ``value`` against type ``tp`` and the bounds in ``meta``; return the clean value."""
    if typing.get_origin(tp) is tuple:
        elem = typing.get_args(tp)[0]
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = (value, value)  # a single number means a square window
        if not isinstance(value, (list, tuple)) or len(value) != 2:
            raise ConfigError(f"{where}: expected a pair like [7, 9], got {value!r}")
        return tuple(_coerce(v, elem, where, meta) for v in value)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            else:
                raise ConfigError(f"{where}: expected an integer, got {value!r}")
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        value = float(value)
    elif tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
    choices = meta.get("choices")
    if choices and value not in choices:
        raise ConfigError(
            f"{where}: {value!r} is not one of {', '.join(map(str, choices))}"
            + (_close(str(value), [str(c) for c in choices]))
        )
    low, high = meta.get("low"), meta.get("high")
    if low is not None and value < low or high is not None and value > high:
        lo = "-inf" if low is None else f"{low:g}"
        hi = "inf" if high is None else f"{high:g}"
        raise ConfigError(f"{where}: {value!r} is out of range [{lo}, {hi}]")
    return value


def _close(word: str, options: list[str]) -> str:
    close = difflib.get_close_matches(word, options, n=3, cutoff=0.5)
    return f" (did you mean {' or '.join(repr(c) for c in close)}?)" if close else ""


_REGISTRY: dict[str, dict[str, Stage]] = {kind: {} for kind in KINDS}


@dataclass(frozen=True)
class NoParams:
    """For stages without parameters."""


def register(
    kind: str,
    name: str,
    params_cls: type = NoParams,
    *,
    needs_cost: bool = False,
    needs_right: bool = False,
    fills_holes: bool = False,
) -> Callable[[Callable], Callable]:
    """Decorator: register ``func(state, params)`` as stage ``name`` of ``kind``.

    The first docstring line is the one-line summary; the rest is the long help.
    Registering a name twice is an error at import time.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown stage kind {kind!r}; valid: {', '.join(KINDS)}")
    if not dataclasses.is_dataclass(params_cls):
        raise TypeError(f"{name}: params_cls must be a dataclass")

    def decorate(func: Callable) -> Callable:
        if name in _REGISTRY[kind]:
            raise ValueError(f"{kind} stage {name!r} registered twice")
        doc = (func.__doc__ or "").strip()
        summary = doc.splitlines()[0] if doc else ""
        _REGISTRY[kind][name] = Stage(
            kind, name, func, params_cls, summary, doc, needs_cost, needs_right, fills_holes
        )
        return func

    return decorate


def _unregister(kind: str, name: str) -> None:
    """Remove a stage (tests and doctests only)."""
    _REGISTRY[kind].pop(name, None)


def _load_builtin_stages() -> None:
    # Importing the stage modules runs their @register decorators.
    from .match import stages  # noqa: F401


def get(kind: str, name: str, *, source: str = "<config>", section: str = "") -> Stage:
    """Return the stage ``name`` of ``kind`` or raise :class:`ConfigError` with close matches."""
    _load_builtin_stages()
    if kind not in _REGISTRY:
        raise ConfigError(f"unknown stage kind {kind!r}; valid: {', '.join(KINDS)}")
    try:
        return _REGISTRY[kind][name]
    except KeyError:
        where = f"{source}: {section or kind}.name"
        raise ConfigError(
            f"{where}: unknown {kind} stage {name!r}" + _suggest(str(name), list(_REGISTRY[kind]))
        ) from None


def names(kind: str, pattern: str = "*") -> list[str]:
    """Sorted names of the registered stages of ``kind`` matching the fnmatch ``pattern``."""
    _load_builtin_stages()
    return sorted(n for n in _REGISTRY[kind] if fnmatch.fnmatch(n, pattern))


def stages(kind: str | None = None) -> list[Stage]:
    """All registered stages (of one kind, or of all kinds in pipeline order)."""
    _load_builtin_stages()
    kinds = [kind] if kind else list(KINDS)
    return [_REGISTRY[k][n] for k in kinds for n in sorted(_REGISTRY[k])]
