"""Sweep specification: a YAML file naming a grid and/or random draws over the axes of a run, and seeds.

Format (every section but ``fixed.scenario`` optional)::

    name: drift-vs-imu
    fixed:                      # held for every run
      scenario: circle
      mode: record-eval         # record-eval (default) | fly | stream
      frontend: sim
      seconds: 10
    grid:                       # full product of the lists, in this order
      imu: [adis16448, bmi088]
      estimator: [msckf, window]
    random:                     # `draws` configurations drawn once, the same at every grid point
      draws: 4
      seed: 0                   # of the draws (not of the runs)
      axes:
        msckf.pixel_sigma_px: {uniform: [0.5, 2.0]}
        msckf.max_clones: {choice: [8, 11, 15]}     # also randint: [lo, hi] (inclusive), loguniform
    seeds: [0, 1, 2]            # or {count: 50, start: 0}
    timeout_s: 600              # per run (a run past it is a row with its error)

Axes: ``mode``, ``scenario``, ``estimator``, ``frontend``, ``imu`` (IMU preset), ``severity`` (of a
``fail-*`` scenario), ``seconds``, and any field of ``MsckfParams`` (``msckf.<field>``), ``WindowParams``
(``window.<field>``) or ``RigConfig`` (``rig.<field>``, mode ``fly`` only), nested by more dots
(``msckf.klt.max_features``). Names and value types are checked against the frozen dataclasses; a bad spec
raises :class:`SpecError` naming the culprit.
"""

from __future__ import annotations

import dataclasses
import itertools
import types
import typing
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np
from viotb.envs.tools.sweep.runs import CORE_AXES, MODES, PARAM_ROOTS, RIG_FIELDS_AS_AXES, Catalog, RunConfig

SECTIONS = ("name", "description", "fixed", "grid", "random", "seeds", "timeout_s")
"""Top-level keys of a spec."""
DISTRIBUTIONS = ("uniform", "loguniform", "randint", "choice")
"""Random-draw distributions."""


class SpecError(ValueError):
    """A sweep spec that cannot run; the message names the culprit."""


@dataclass(frozen=True)
class RandomAxes:
    """Random draws of a spec.

    Attributes:
        draws: Configurations drawn (each run at every grid point and seed).
        seed: Seed of the draws.
        axes: ``(axis, (distribution, arguments))`` pairs.
    """

    draws: int
    seed: int
    axes: tuple[tuple[str, tuple[str, tuple]], ...]


@dataclass(frozen=True)
class SweepSpec:
    """A parsed, validated spec (see the module docstring).

    Attributes:
        name: Sweep name.
        fixed: ``(axis, value)`` pairs held for every run.
        grid: ``(axis, values)`` pairs, expanded as a product.
        random: Random draws, or None.
        seeds: Run seeds.
        timeout_s: Per-run timeout (s), or None.
        description: Free text.
    """

    name: str
    fixed: tuple[tuple[str, Any], ...]
    grid: tuple[tuple[str, tuple], ...] = ()
    random: RandomAxes | None = None
    seeds: tuple[int, ...] = (0,)
    timeout_s: float | None = None
    description: str = ""

    def expand(self) -> list[RunConfig]:
        """Every run: grid points x draws x seeds (validated when the spec was parsed)."""
        return _expand(self)

    def as_dict(self) -> dict:
        """The spec in its YAML form (what ``spec.yaml`` of a sweep folder holds)."""
        out: dict = {"name": self.name, "fixed": dict(self.fixed), "grid": {k: list(v) for k, v in self.grid}}
        if self.description:
            out["description"] = self.description
        if self.random is not None:
            axes = {k: {dist: list(args)} for k, (dist, args) in self.random.axes}
            out["random"] = {"draws": self.random.draws, "seed": self.random.seed, "axes": axes}
        out["seeds"] = list(self.seeds)
        if self.timeout_s is not None:
            out["timeout_s"] = self.timeout_s
        return out


def load_spec(path: Path | str, cat: Catalog | None = None) -> SweepSpec:
    """Read and validate a YAML spec file (SpecError naming the file and the culprit)."""
    import yaml

    p = Path(path)
    if not p.is_file():
        raise SpecError(f"spec {p}: no such file")
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as exc:
        raise SpecError(f"spec {p}: invalid YAML ({exc})") from None
    return parse_spec(data, cat, source=str(p), default_name=p.stem)


def parse_spec(
    data: Any, cat: Catalog | None = None, source: str = "spec", default_name: str = "sweep"
) -> SweepSpec:
    """Validate a spec given as a dict (the YAML's content).

    Args:
        data: The spec.
        cat: Names to check against (default: :func:`~viotb.envs.tools.sweep.runs.catalog`).
        source: Name used in error messages.
        default_name: Sweep name when the spec has none.

    Raises:
        SpecError: Unknown section, axis or parameter; bad value type; empty grid list; unknown scenario,
            estimator, front end, IMU preset or mode; no scenario.
    """
    if cat is None:
        from viotb.envs.tools.sweep.runs import catalog

        cat = catalog()

    def fail(msg: str) -> SpecError:
        return SpecError(f"{source}: {msg}")

    if not isinstance(data, dict):
        raise fail(f"expected a mapping at the top level, got {type(data).__name__}")
    unknown = sorted(set(data) - set(SECTIONS))
    if unknown:
        raise fail(f"unknown section(s) {unknown}; allowed: {', '.join(SECTIONS)}")
    fixed = _mapping(data.get("fixed", {}), "fixed", fail)
    grid = _mapping(data.get("grid", {}), "grid", fail)
    fixed_items = tuple((k, _check_axis(k, v, cat, f"fixed.{k}", fail)) for k, v in fixed.items())
    grid_items = []
    for axis, values in grid.items():
        if not isinstance(values, list):
            raise fail(f"grid.{axis}: expected a list of values, got {type(values).__name__}")
        if not values:
            raise fail(f"grid.{axis}: empty list (a grid axis needs at least one value)")
        grid_items.append((axis, tuple(_check_axis(axis, v, cat, f"grid.{axis}", fail) for v in values)))
    rnd = _parse_random(data.get("random"), cat, fail)
    names = (
        [k for k, _ in fixed_items] + [k for k, _ in grid_items] + ([k for k, _ in rnd.axes] if rnd else [])
    )
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise fail(f"axis {dup} given more than once (fixed, grid and random are exclusive)")
    if "scenario" not in names:
        raise fail("no scenario: give fixed.scenario or grid.scenario")
    spec = SweepSpec(
        name=str(data.get("name", default_name)),
        description=str(data.get("description", "")),
        fixed=fixed_items,
        grid=tuple(grid_items),
        random=rnd,
        seeds=_parse_seeds(data.get("seeds", [0]), fail),
        timeout_s=_parse_timeout(data.get("timeout_s"), fail),
    )
    runs = spec.expand()  # draws validated here, and every run's combination
    for cfg in runs:
        _check_run(cfg, cat, fail)
    return spec


def _mapping(value: Any, section: str, fail) -> dict:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise fail(f"{section}: expected a mapping of axis: value, got {type(value).__name__}")
    return value


def _parse_seeds(value: Any, fail) -> tuple[int, ...]:
    if isinstance(value, dict):
        if set(value) - {"count", "start"} or not isinstance(value.get("count"), int):
            raise fail(f"seeds: expected a list of ints or {{count: N, start: S}}, got {value}")
        start = value.get("start", 0)
        if not isinstance(start, int) or isinstance(start, bool) or value["count"] < 1:
            raise fail(f"seeds: count must be >= 1 and start an int, got {value}")
        return tuple(range(start, start + value["count"]))
    if not isinstance(value, list) or not value:
        raise fail(f"seeds: expected a non-empty list of ints, got {value!r}")
    bad = [s for s in value if not isinstance(s, int) or isinstance(s, bool) or s < 0]
    if bad:
        raise fail(f"seeds: not non-negative ints: {bad}")
    return tuple(dict.fromkeys(value))


def _parse_timeout(value: Any, fail) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
        raise fail(f"timeout_s: expected a positive number of seconds, got {value!r}")
    return float(value)


def _parse_random(value: Any, cat: Catalog, fail) -> RandomAxes | None:
    if value is None:
        return None
    if not isinstance(value, dict) or set(value) - {"draws", "seed", "axes"}:
        raise fail(f"random: expected {{draws: N, seed: S, axes: {{...}}}}, got {value!r}")
    draws, seed = value.get("draws", 1), value.get("seed", 0)
    if not isinstance(draws, int) or isinstance(draws, bool) or draws < 1:
        raise fail(f"random.draws: expected an int >= 1, got {draws!r}")
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise fail(f"random.seed: expected an int, got {seed!r}")
    axes = _mapping(value.get("axes"), "random.axes", fail)
    if not axes:
        raise fail("random.axes: empty (name at least one axis to draw)")
    items = []
    for axis, dist in axes.items():
        where = f"random.axes.{axis}"
        _check_axis_name(axis, cat, where, fail)
        if not isinstance(dist, dict) or len(dist) != 1 or next(iter(dist)) not in DISTRIBUTIONS:
            raise fail(f"{where}: expected one of {{{': [...], '.join(DISTRIBUTIONS)}: [...]}}, got {dist!r}")
        kind, args = next(iter(dist.items()))
        if not isinstance(args, list) or not args:
            raise fail(f"{where}.{kind}: expected a non-empty list, got {args!r}")
        if kind != "choice":
            if len(args) != 2 or not all(
                isinstance(a, int | float) and not isinstance(a, bool) for a in args
            ):
                raise fail(f"{where}.{kind}: expected [low, high] numbers, got {args!r}")
            if not args[0] <= args[1] or (kind == "loguniform" and args[0] <= 0):
                raise fail(f"{where}.{kind}: expected low <= high (and low > 0 for loguniform), got {args!r}")
            if kind == "randint" and not all(isinstance(a, int) for a in args):
                raise fail(f"{where}.randint: expected [low, high] ints, got {args!r}")
        else:
            for v in args:
                _check_axis(axis, v, cat, f"{where}.choice", fail)
        items.append((axis, (kind, tuple(args))))
    return RandomAxes(draws=draws, seed=seed, axes=tuple(items))


def _draws(rnd: RandomAxes | None) -> list[dict]:
    """The drawn configurations (the same for a given spec)."""
    if rnd is None:
        return [{}]
    rng = np.random.default_rng(rnd.seed)
    out = []
    for _ in range(rnd.draws):
        draw = {}
        for axis, (kind, args) in rnd.axes:
            if kind == "uniform":
                draw[axis] = float(rng.uniform(args[0], args[1]))
            elif kind == "loguniform":
                draw[axis] = float(np.exp(rng.uniform(np.log(args[0]), np.log(args[1]))))
            elif kind == "randint":
                draw[axis] = int(rng.integers(args[0], args[1], endpoint=True))
            else:
                draw[axis] = args[int(rng.integers(len(args)))]
        out.append(draw)
    return out


def _expand(spec: SweepSpec) -> list[RunConfig]:
    axes = [k for k, _ in spec.grid]
    runs: list[RunConfig] = []
    for point in itertools.product(*(v for _, v in spec.grid)):
        for draw in _draws(spec.random):
            values = {**dict(spec.fixed), **dict(zip(axes, point, strict=True)), **draw}
            core = {k: v for k, v in values.items() if k in CORE_AXES}
            params = {k: v for k, v in values.items() if k not in CORE_AXES}
            for seed in spec.seeds:
                runs.append(RunConfig.from_dict({**core, **params, "seed": seed}))
    return runs


def _check_run(cfg: RunConfig, cat: Catalog, fail) -> None:
    """Combinations: scenario known for the mode, ``rig.*`` with ``fly`` only, severity with ``fail-*``."""
    known = cat.scenarios.get(cfg.mode, ())
    if cfg.scenario not in known:
        raise fail(f"unknown scenario {cfg.scenario!r} for mode {cfg.mode}; known: {', '.join(known)}")
    rig = [name for name, _ in cfg.params if name.startswith("rig.")]
    if rig and cfg.mode != "fly":
        raise fail(f"{rig} apply to mode 'fly' only (this run is {cfg.mode})")
    stream = [name for name, _ in cfg.params if name.startswith("stream.")]
    if stream and cfg.mode != "stream":
        raise fail(f"{stream} apply to mode 'stream' only (this run is {cfg.mode})")
    if cfg.mode == "stream" and (cfg.frontend != "sim" or cfg.estimator not in ("msckf", "window")):
        raise fail(
            f"mode 'stream' runs msckf or window on simulated features (frontend 'sim'), got estimator "
            f"{cfg.estimator!r}, frontend {cfg.frontend!r}"
        )
    if cfg.severity is not None and "fail-" not in cfg.scenario:
        raise fail(f"severity applies to fail-* scenarios only, got scenario {cfg.scenario!r}")
    # Draws are validated here: a uniform draw on an int field is refused.
    for name, value in cfg.params:
        _check_param_value(name, value, cat, name, fail)


def _check_axis_name(axis: Any, cat: Catalog, where: str, fail) -> None:
    if not isinstance(axis, str):
        raise fail(f"{where}: axis names are strings, got {axis!r}")
    if axis == "seed":
        raise fail(f"{where}: the seeds go in the `seeds` section, not an axis")
    if axis in CORE_AXES:
        return
    root, _, rest = axis.partition(".")
    if root not in PARAM_ROOTS or not rest:
        allowed = ", ".join(CORE_AXES) + ", " + ", ".join(f"{r}.<field>" for r in PARAM_ROOTS)
        raise fail(f"{where}: unknown axis {axis!r}; allowed: {allowed}")
    if root == "rig" and rest.split(".")[0] in RIG_FIELDS_AS_AXES:
        raise fail(f"{where}: {axis!r} is set by the {RIG_FIELDS_AS_AXES[rest.split('.')[0]]!r} axis")
    _field_type(cat.param_roots[root], rest, axis, where, fail)


def _check_axis(axis: Any, value: Any, cat: Catalog, where: str, fail) -> Any:
    """Validate ``axis: value``; returns the canonical value (floats for float fields)."""
    _check_axis_name(axis, cat, where, fail)
    if axis in CORE_AXES:
        return _check_core(axis, value, cat, where, fail)
    return _check_param_value(axis, value, cat, where, fail)


def _check_core(axis: str, value: Any, cat: Catalog, where: str, fail) -> Any:
    choices = {
        "mode": MODES,
        "estimator": cat.estimators,
        "frontend": cat.frontends,
        "imu": cat.imu_presets,
        "scenario": tuple(sorted({s for names in cat.scenarios.values() for s in names})),
    }
    if axis in choices:
        if axis == "imu" and value is None:
            return None
        if not isinstance(value, str):
            raise fail(f"{where}: expected a string, got {type(value).__name__} {value!r}")
        if value not in choices[axis]:
            raise fail(f"{where}: unknown {axis} {value!r}; known: {', '.join(choices[axis])}")
        return value
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise fail(f"{where}: expected a number, got {type(value).__name__} {value!r}")
    if axis == "seconds" and not value > 0:
        raise fail(f"{where}: seconds must be > 0, got {value}")
    if axis == "severity" and not value >= 0:
        raise fail(f"{where}: severity must be >= 0, got {value}")
    return float(value)


def _field_type(cls: type, path: str, axis: str, where: str, fail) -> Any:
    """The type annotation of dotted field ``path`` of dataclass ``cls``."""
    head, _, rest = path.partition(".")
    fields = {f.name for f in dataclasses.fields(cls)}
    if head not in fields:
        raise fail(
            f"{where}: unknown parameter {axis!r}: {cls.__name__} has no field {head!r}; "
            f"fields: {', '.join(sorted(fields))}"
        )
    hint = typing.get_type_hints(cls)[head]
    if dataclasses.is_dataclass(hint):
        if not rest:
            sub = ", ".join(f.name for f in dataclasses.fields(hint))
            raise fail(f"{where}: {axis!r} is a group ({hint.__name__}); name one of its fields: {sub}")
        return _field_type(hint, rest, axis, where, fail)
    if rest:
        raise fail(f"{where}: unknown parameter {axis!r}: {cls.__name__}.{head} has no fields")
    return hint


def _check_param_value(axis: str, value: Any, cat: Catalog, where: str, fail) -> Any:
    root, _, rest = axis.partition(".")
    hint = _field_type(cat.param_roots[root], rest, axis, where, fail)
    ok, canon = _conform(hint, value)
    if not ok:
        raise fail(
            f"{where}: bad value for {axis!r}: expected {_type_name(hint)}, got "
            f"{type(value).__name__} {value!r}"
        )
    return canon


def _conform(hint: Any, value: Any) -> tuple[bool, Any]:
    """Whether ``value`` (from YAML) fits annotation ``hint``, and its canonical JSON form."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return True, None
        for arm in args:
            if arm is not type(None):
                ok, canon = _conform(arm, value)
                if ok:
                    return True, canon
        return False, None
    if origin is tuple:
        if not isinstance(value, list | tuple):
            return False, None
        arms = [args[0]] * len(value) if len(args) == 2 and args[1] is Ellipsis else list(args)
        if len(arms) != len(value):
            return False, None
        parts = [_conform(a, v) for a, v in zip(arms, value, strict=True)]
        return all(ok for ok, _ in parts), tuple(c for _, c in parts)
    if hint is typing.Any:
        return True, value
    if isinstance(hint, type) and issubclass(hint, Enum):
        for member in hint:
            if value in (member.name, member.value):
                return True, member.value
        return False, None
    if hint is bool:
        return isinstance(value, bool), value
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool), value
    if hint is float:
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        return ok, float(value) if ok else None
    if hint is str:
        return isinstance(value, str), value
    return False, None


def _type_name(hint: Any) -> str:
    if isinstance(hint, type) and issubclass(hint, Enum):
        return "one of " + ", ".join(repr(m.value) for m in hint)
    return getattr(hint, "__name__", None) or str(hint)
