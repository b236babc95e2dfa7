"""Named, documented, validated components: the stage registry.

A stage is a function registered under a ``(kind, name)`` pair together with a frozen
dataclass of parameters and a :class:`StageTraits` record. Each parameter field is declared
with :func:`param`, which records its default, one-line help, unit and range or choices;
``stereocli stages`` prints them and :func:`Stage.make_params` validates user values against
them. The traits say what the pipeline must know about the stage (memory, the volumes it
reads, the variants it offers); the pipeline reads nothing else about a stage.

The registry knows no stage: a stage module registers its stages when it is imported.
:mod:`stereocli.matching.stages` :func:`declare` says which module registers each built-in stage,
and the registry imports that module the first time one of its stages is asked for
(:func:`get`), or every declared module when the stages are listed (:func:`names`,
:func:`stages`). So a run imports only the stage modules, and with them the compiled kernels,
that its config names.

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
import fnmatch
import importlib
import math
import typing
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from .errors import ConfigError, did_you_mean, excerpt

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


Predicate = Callable[..., bool]


@dataclass(frozen=True)
class StageTraits:
    """What the matching pipeline must know about a stage, declared once at registration.

    Every field defaults to "no special needs". Predicates take the stage's params (and, for
    ``needs_second_best``/``needs_right_costs``, the :class:`~stereocli.matching.state.MatchState`
    first); give them a docstring, which ``stereocli stages -v`` prints.
    """

    # -- every stage --------------------------------------------------------------------------
    #: Reads the left view's colour channels: True, False (only its grey, ``state.gray("left")``,
    #: or not at all) or ``f(params) -> bool`` (a ``color`` switch). When no stage of a config
    #: reads them, the pipeline takes the left view's grey straight from the input (no float
    #: copy of the colours).
    reads_left_colour: bool | Predicate = True
    #: The same for the right view. When no stage reads its colours, preprocessing (row_align)
    #: also moves one channel instead of three.
    reads_right_colour: bool | Predicate = True

    # -- refinement stages --------------------------------------------------------------------
    #: Reads the cost volume: runs inside each row strip, before the volume is dropped.
    needs_cost: bool = False
    #: Needs the right-view disparity (the pipeline computes it from the final volume).
    needs_right: bool = False
    #: Fills invalid pixels (``match --keep-invalid`` skips it).
    fills_holes: bool = False
    #: Sets ``state.confidence`` whenever ``state.wants.confidence`` (``match --confidence``):
    #: a config makes a confidence map exactly when one of its refinements says so.
    produces_confidence: bool = False
    #: ``f(state, params)``: the same stage reading ``state.winner`` (the costs kept around each
    #: winner) instead of the volume, with the same result. Lets the volume go unbuilt.
    on_winner_costs: Callable | None = None
    #: ``f(state, params) -> bool``: reads ``winner.second`` (best cost beyond ±1 of the winner).
    needs_second_best: Predicate | None = None
    #: ``f(state, params) -> bool``: reads ``winner.costs_right`` (costs around the right-view winners).
    needs_right_costs: Predicate | None = None
    #: ``f(params) -> bool``: reads the optimizer's integer maps (``state.integer_disparity``).
    keeps_integer: Predicate | None = None
    #: Reads ``state.mirrored_disparity``: the map of the same pipeline, up to this stage, run
    #: on the mirrored pair (both images flipped left-right and swapped), flipped back, so it is
    #: referenced to the right image. The pipeline runs it just before the stage.
    needs_mirrored: bool = False
    #: ``f(params, note) -> params``: a preprocess stage's params for that mirrored run, from
    #: the note the stage left on the pair (``state.notes``; None if it left none): they repeat
    #: its effect on the mirrored pair instead of measuring it again.
    mirrored_params: Callable | None = None
    #: ``f(params, note) -> params``: a preprocess stage's params that repeat on another pair of
    #: the same rig what it did on this one (its note), without measuring again; e.g. the later
    #: frames of a sequence (:mod:`stereocli.sequence`).
    repeated_params: Callable | None = None

    # -- cost stages ----------------------------------------------------------------------
    #: ``f(state, params, winner: bool)``: cost + WTA in one pass, never storing the volume
    #: (sets ``disparity`` and, if ``winner``, ``state.winner``).
    fused_wta: Callable | None = None
    #: ``f(state, params, runs) -> (costs, cost_max)``: the costs on a windowed SGM's runs only.
    windowed: Callable | None = None
    #: Bytes per cell of the integer volume the stage leaves when ``state.wants.integer_cost``
    #: (0: always float32).
    integer_cost_itemsize: int = 0
    #: ``f(params) -> params``: the stage's params at a coarse-to-fine optimizer's coarse level,
    #: whose map only bounds the full-resolution search: where a costlier cost variant does
    #: not change those bounds, the coarse level runs the cheaper one.
    coarse_params: Callable | None = None

    # -- optimizers -----------------------------------------------------------------------
    #: Takes each pixel's lowest cost and nothing else, so a cost stage's ``fused_wta`` may
    #: stand in for cost + this optimizer.
    winner_take_all: bool = False
    #: Reads an integer (uint8/uint16) volume straight from the cost stage.
    accepts_integer_cost: bool = False
    #: ``f(params) -> bool``: the stage owns the cost computation. It is called as
    #: ``func(state, params, cost=<cost StageCall>)``; when this returns True and no aggregation
    #: stage sits between them, the pipeline does not run the cost stage (the optimizer computes
    #: the costs itself, e.g. only on its coarse-to-fine windows).
    runs_cost: Predicate | None = None
    #: ``f(params, height, width, ndisp) -> params``: params with which a tiny pair (a warm-up
    #: that loads the kernels before a run's first pair is timed) takes the code path a pair of
    #: this size takes with ``params``, when the path depends on the size.
    small_twin: Callable | None = None
    #: ``f(params, width, ndisp) -> bytes``: fixed buffers per row strip (memory planner).
    buffer_bytes: Callable | None = None
    #: ``f(params, height, width, ndisp, image_rows) -> bytes or None``: an optimizer's own
    #: estimate of the peak bytes of its search on a strip of ``height`` rows of an image of
    #: ``image_rows`` rows (volumes, per-pixel and row buffers), when it knows
    #: better than the volume count (a coarse-to-fine search never holds the whole volume);
    #: None: the volume count of ``volume_copies`` applies.
    strip_bytes: Callable | None = None
    #: The stage's function takes ``coarse_level=f(state, params, cost) -> disparities``, which
    #: its coarse-to-fine search calls instead of computing its coarse level (the warm-up
    #: compiles the fine level's kernels in one process while another compiles the coarse level's).
    takes_coarse_level: bool = False

    # -- memory (the planner: volumes of every stage that holds them, whole-image maps) -------
    #: Extra (H, W, D) float32-sized volumes held beside the input (a uint16 copy counts 0.5);
    #: None: 0 for a cost stage (just its output), 1 for the others.
    volume_copies: float | None = None
    #: ``volume_copies`` when the input is the cost stage's integer volume.
    integer_volume_copies: float | None = None
    #: Preprocess and map-refinement stages (they see the whole image): extra (H, W) float32
    #: maps the stage holds at its peak beside the pair's views and maps; a preprocess stage's
    #: count is per channel of the views (3 for colour views). None: 3.
    map_copies: float | None = None

    def declared(self) -> dict[str, Any]:
        """The fields that differ from the defaults (what ``stereocli stages -v`` prints)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) != f.default}

    def describe(self) -> list[str]:
        """``name: value`` lines for the declared traits; callables by their docstring or name."""
        lines = []
        for name, value in self.declared().items():
            if callable(value):
                first_paragraph = (value.__doc__ or "").strip().split("\n\n")[0]
                value = " ".join(first_paragraph.split()) or getattr(value, "__name__", "function")
            lines.append(f"{name}: {value}")
        return lines


NO_TRAITS = StageTraits()


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
    """A registered stage: ``func(state, params)`` runs it on a
    :class:`stereocli.matching.state.MatchState`; ``traits`` tell the pipeline how."""

    kind: str
    name: str
    func: Callable
    params_cls: type
    summary: str
    doc: str
    traits: StageTraits = NO_TRAITS

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
                    f"{where}{excerpt(key)}: unknown parameter of {self.kind} stage '{self.name}'"
                    + _suggest(key, names)
                )
            kwargs[key] = _coerce(value, hints[key], f"{where}{key}", self._meta(key))
        return self.params_cls(**kwargs)

    def _meta(self, key: str) -> Mapping[str, Any]:
        return next(f.metadata for f in dataclasses.fields(self.params_cls) if f.name == key)


def _type_name(tp: Any) -> str:
    if typing.get_origin(tp) is tuple:
        return "pair of " + _type_name(typing.get_args(tp)[0])
    return getattr(tp, "__name__", str(tp))


def _suggest(word: str, options: list[str]) -> str:
    if not options:
        return "; it takes no parameters"
    return did_you_mean(word, options) + f"; valid: {', '.join(sorted(options))}"


def _coerce(value: Any, tp: Any, where: str, meta: Mapping[str, Any]) -> Any:
    """Check ``value`` against type ``tp`` and the bounds in ``meta``; return the clean value."""
    if typing.get_origin(tp) is tuple:
        elem = typing.get_args(tp)[0]
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = (value, value)  # a single number means a square window
        if not isinstance(value, (list, tuple)) or len(value) != 2:
            raise ConfigError(f"{where}: expected a pair like [7, 9], got {excerpt(value, quote=True)}")
        return tuple(_coerce(v, elem, where, meta) for v in value)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {excerpt(value, quote=True)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            else:
                raise ConfigError(f"{where}: expected an integer, got {excerpt(value, quote=True)}")
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {excerpt(value, quote=True)}")
        value = float(value)
        if not math.isfinite(value):  # NaN passes every comparison below
            raise ConfigError(f"{where}: expected a finite number, got {excerpt(value, quote=True)}")
    elif tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {excerpt(value, quote=True)}")
    choices = meta.get("choices")
    if choices and value not in choices:
        raise ConfigError(
            f"{where}: {excerpt(value, quote=True)} is not one of {', '.join(map(str, choices))}"
            + did_you_mean(str(value), [str(c) for c in choices])
        )
    low, high = meta.get("low"), meta.get("high")
    if low is not None and value < low or high is not None and value > high:
        lo = "-inf" if low is None else f"{low:g}"
        hi = "inf" if high is None else f"{high:g}"
        raise ConfigError(f"{where}: {excerpt(value, quote=True)} is out of range [{lo}, {hi}]")
    return value


_REGISTRY: dict[str, dict[str, Stage]] = {kind: {} for kind in KINDS}
#: kind -> stage name -> the module that registers it when imported (:func:`declare`).
_DECLARED: dict[str, dict[str, str]] = {kind: {} for kind in KINDS}


@dataclass(frozen=True)
class NoParams:
    """For stages without parameters."""


def register(
    kind: str,
    name: str,
    params_cls: type = NoParams,
    *,
    traits: StageTraits = NO_TRAITS,
) -> Callable[[Callable], Callable]:
    """Decorator: register ``func(state, params)`` as stage ``name`` of ``kind`` with ``traits``.

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
        _REGISTRY[kind][name] = Stage(kind, name, func, params_cls, summary, doc, traits)
        return func

    return decorate


def _unregister(kind: str, name: str) -> None:
    """Remove a stage (tests and doctests only)."""
    _REGISTRY[kind].pop(name, None)


def declare(module: str, kind: str, stage_names) -> None:
    """Importing ``module`` (a dotted name) registers these stages of ``kind``: it is imported
    when one of them is first asked for, so stage modules load only when a run uses them."""
    if kind not in KINDS:
        raise ValueError(f"unknown stage kind {kind!r}; valid: {', '.join(KINDS)}")
    for name in stage_names:
        _DECLARED[kind][name] = module


def _import_declared(kinds) -> None:
    """Import every declared module that registers a stage of ``kinds`` not registered yet."""
    pending = {module for k in kinds for n, module in _DECLARED[k].items() if n not in _REGISTRY[k]}
    for module in sorted(pending):
        importlib.import_module(module)


def get(kind: str, name: str, *, source: str = "<config>", section: str = "") -> Stage:
    """Return the stage ``name`` of ``kind`` (importing its declared module on first use) or
    raise :class:`ConfigError` with close matches."""
    if kind not in _REGISTRY:
        raise ConfigError(f"unknown stage kind {kind!r}; valid: {', '.join(KINDS)}")
    stage = _REGISTRY[kind].get(name)
    if stage is None and name in _DECLARED[kind]:
        importlib.import_module(_DECLARED[kind][name])
        stage = _REGISTRY[kind].get(name)
    if stage is None:
        where = f"{source}: {section or kind}.name"
        known = sorted(set(_REGISTRY[kind]) | set(_DECLARED[kind]))
        raise ConfigError(f"{where}: unknown {kind} stage {excerpt(name, quote=True)}" + _suggest(str(name), known))
    return stage


def names(kind: str, pattern: str = "*") -> list[str]:
    """Sorted names of the registered stages of ``kind`` matching the fnmatch ``pattern``."""
    _import_declared([kind])
    return sorted(n for n in _REGISTRY[kind] if fnmatch.fnmatch(n, pattern))


def stages(kind: str | None = None) -> list[Stage]:
    """All registered stages (of one kind, or of all kinds in pipeline order)."""
    kinds = [kind] if kind else list(KINDS)
    _import_declared(kinds)
    return [_REGISTRY[k][n] for k in kinds for n in sorted(_REGISTRY[k])]


def markdown_reference(chosen: list[Stage]) -> str:
    """A Markdown reference of ``chosen`` stages: per kind, each stage's documentation, a table
    of its parameters and its traits (``stereocli stages --format markdown``, docs/methods.md)."""
    lines = ["# Matching stages", "",
             "Every registered stage, its parameters and its traits. Generated by",
             "`stereocli stages --format markdown > docs/methods.md`; a test checks it is current.", ""]
    current = None
    for s in chosen:
        if s.kind != current:
            current = s.kind
            lines += [f"## {s.kind}", ""]
        lines += [f"### `{s.name}`", "", *_dedent(s.doc), ""]
        specs = s.param_specs()
        if specs:
            lines += ["| parameter | type | default | range | help |", "|---|---|---|---|---|"]
            for p in specs:
                default = list(p.default) if isinstance(p.default, tuple) else p.default
                unit = f" {p.unit}" if p.unit else ""
                cells = [f"`{p.name}`", p.type_name, f"`{default}`{unit}", p.describe_range(), p.help]
                lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
            lines.append("")
        traits = s.traits.describe()
        if traits:
            lines += ["Traits: " + "; ".join(f"`{t.split(': ', 1)[0]}`: {t.split(': ', 1)[1]}" for t in traits), ""]
    return "\n".join(lines).rstrip() + "\n"


def _dedent(doc: str) -> list[str]:
    import textwrap

    first, _, rest = doc.partition("\n")
    return [first.strip(), *textwrap.dedent(rest).splitlines()]
