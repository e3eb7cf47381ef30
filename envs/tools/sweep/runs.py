"""One run of a sweep: :class:`RunConfig` and :func:`run_config` (in this process, no Ray).

This is the only module of the sweep that imports the testbed's run functions (``viotb.envs.record``,
``viotb.envs.evaluate``, ``viotb.envs.fly``, ``viotb.envs.closed_loop``, ``viotb.envs.scenarios``): when
they move, update the imports here and nowhere else. They are imported inside the functions, so that the
CLI and the spec parser stay light.

Modes:

- ``record-eval``: :func:`record_scenario` into a temporary folder, then :func:`evaluate_dataset` on it (the
  ``viotb record`` + ``viotb eval`` pair); the metrics are the eval JSON, plus the recording's under
  ``record/``.
- ``fly``: :func:`fly` (``viotb fly``); the metrics are its JSON.

Parameter overrides (``msckf.*``, ``window.*``, ``rig.*`` and the ``imu`` axis): the run functions take no
estimator or rig settings today, so for the duration of one run the factory each of them calls is swapped
(``unittest.mock.patch.object``) for one that applies the overrides: ``evaluate.make_estimator`` and
``closed_loop.make_estimator`` (estimator settings), ``fly.ClosedLoopSim`` (rig fields),
``record.get_scenario`` / ``failures.failure_record_scenario`` (the IMU preset of a recording). A moved
attribute makes ``patch.object`` raise, and ``tests/test_sweep.py`` checks that an override changes the
result. Once those functions take ``params=`` / ``window_params=`` / ``rig=`` arguments, pass them instead.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tempfile
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any
from unittest.mock import patch

MODES = ("record-eval", "fly")
"""Run modes: record then evaluate (open loop), or a closed-loop flight."""
CORE_AXES = ("mode", "scenario", "estimator", "frontend", "imu", "severity", "seconds")
"""Axes of a run besides the seed and the dataclass parameters."""
PARAM_ROOTS = ("msckf", "window", "rig")
"""Prefixes of parameter axes: ``msckf.<MsckfParams field>``, ``window.<WindowParams field>``,
``rig.<RigConfig field>`` (nested dataclasses by more dots: ``msckf.klt.max_features``)."""
RIG_FIELDS_AS_AXES = {"estimator": "estimator", "frontend": "frontend", "imu_preset": "imu"}
"""RigConfig fields that the core axes set (naming them as ``rig.*`` is refused)."""
_DROP = {
    "record-eval": {"dataset", "estimator", "frontend"},
    "record": {"out", "scenario", "seed"},
    "fly": {"scenario", "estimator", "frontend", "seed"},
}
"""Keys of a run's JSON that echo the configuration or name temporary paths (not metrics)."""


@dataclass(frozen=True)
class RunConfig:
    """Everything that defines one run; the same config gives the same metrics.

    Attributes:
        scenario: Scenario name (``viotb scenarios``; a ``record`` one for ``record-eval``, a ``fly`` one
            for ``fly``).
        mode: One of :data:`MODES`.
        estimator: ``msckf``, ``window``, ``imu-only`` or ``ground-truth``.
        frontend: ``klt`` (images) or ``sim`` (simulated features).
        imu: IMU preset (``adis16448``, ``bmi088``, ...); None keeps the scenario's.
        severity: Severity of a ``fail-*`` / ``fly-fail-*`` scenario; None = its default.
        seconds: Duration (s); None = the scenario's default.
        seed: Seed of every random component of the run.
        params: Sorted ``(dotted name, JSON value)`` overrides of ``MsckfParams``, ``WindowParams`` and
            ``RigConfig`` fields (lists stored as tuples).
    """

    scenario: str
    mode: str = "record-eval"
    estimator: str = "msckf"
    frontend: str = "klt"
    imu: str | None = None
    severity: float | None = None
    seconds: float | None = None
    seed: int = 0
    params: tuple[tuple[str, Any], ...] = ()

    def as_dict(self) -> dict:
        """Flat JSON-able dict: the core axes, ``seed`` and one key per parameter."""
        out = {axis: getattr(self, axis) for axis in CORE_AXES}
        out["seed"] = self.seed
        out.update({name: _jsonable(value) for name, value in self.params})
        return out

    @classmethod
    def from_dict(cls, data: dict) -> RunConfig:
        """Inverse of :meth:`as_dict` (dotted keys are parameters)."""
        core = {k: v for k, v in data.items() if "." not in k}
        params = tuple(sorted((k, _frozen(v)) for k, v in data.items() if "." in k))
        return cls(**core, params=params)

    @property
    def run_id(self) -> str:
        """Hash of the whole configuration (stable JSON, sorted keys): the resume key."""
        return _digest(self.as_dict())

    @property
    def config_id(self) -> str:
        """Hash of the configuration without the seed: runs that differ only by seed share it."""
        data = self.as_dict()
        data.pop("seed")
        return _digest(data)


@dataclass(frozen=True)
class Catalog:
    """Names a spec may use, read from the testbed's registries.

    Attributes:
        scenarios: Scenario names per mode.
        estimators: Estimator names.
        frontends: Front-end names.
        imu_presets: IMU preset names.
        param_roots: Dataclass of each parameter prefix (:data:`PARAM_ROOTS`).
    """

    scenarios: dict[str, tuple[str, ...]]
    estimators: tuple[str, ...]
    frontends: tuple[str, ...]
    imu_presets: tuple[str, ...]
    param_roots: dict[str, type]


def catalog() -> Catalog:
    """The current registries (imports the scenario modules: about a second)."""
    from viotb.envs.closed_loop import RigConfig  # noqa: PLC0415
    from viotb.envs.imu_model import imu_preset_names  # noqa: PLC0415
    from viotb.envs.scenarios import list_scenarios  # noqa: PLC0415
    from viotb.vio.factory import ESTIMATOR_NAMES, FRONTEND_NAMES  # noqa: PLC0415
    from viotb.vio.msckf import MsckfParams  # noqa: PLC0415
    from viotb.vio.window import WindowParams  # noqa: PLC0415

    items = list_scenarios()
    kinds = {"record-eval": "record", "fly": "fly"}
    return Catalog(
        scenarios={
            mode: tuple(s["name"] for s in items if s["kind"] == kind) for mode, kind in kinds.items()
        },
        estimators=tuple(ESTIMATOR_NAMES),
        frontends=tuple(FRONTEND_NAMES),
        imu_presets=tuple(imu_preset_names()),
        param_roots={"msckf": MsckfParams, "window": WindowParams, "rig": RigConfig},
    )


def run_config(cfg: RunConfig) -> dict:
    """Run one configuration in this process (no Ray) and return its flat metrics.

    BLAS is limited to one thread for the run (determinism: a threaded BLAS sums in another order).

    Args:
        cfg: The run.

    Returns:
        The run's JSON flattened: nested keys joined by ``/`` (``record/frames``), lists as JSON strings;
        keys that echo the configuration or name temporary paths are left out.

    Raises:
        ValueError: Unknown mode, scenario, estimator, ...; whatever the run raises.
    """
    from threadpoolctl import threadpool_limits  # noqa: PLC0415

    os.environ.setdefault("MUJOCO_GL", "egl")
    groups = split_params(cfg.params)
    with threadpool_limits(1):
        if cfg.mode == "record-eval":
            return _record_eval(cfg, groups)
        if cfg.mode == "fly":
            return _fly(cfg, groups)
    raise ValueError(f"unknown mode {cfg.mode!r}; allowed: {', '.join(MODES)}")


def split_params(params: tuple[tuple[str, Any], ...]) -> dict[str, dict[str, Any]]:
    """``{"msckf": {field path: value}, "window": {...}, "rig": {...}}`` from dotted overrides."""
    groups: dict[str, dict[str, Any]] = {root: {} for root in PARAM_ROOTS}
    for name, value in params:
        root, _, rest = name.partition(".")
        if root not in groups:
            raise ValueError(f"unknown parameter {name!r}; prefixes: {', '.join(PARAM_ROOTS)}")
        groups[root][rest] = value
    return groups


def apply_overrides(obj: Any, overrides: dict[str, Any]) -> Any:
    """A copy of frozen dataclass ``obj`` with dotted field paths replaced (nested dataclasses too).

    JSON values are converted back: a list to a tuple, a string to the field's enum.
    """
    if not overrides:
        return obj
    direct: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for path, value in overrides.items():
        head, _, rest = path.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            current = getattr(obj, head)
            direct[head] = type(current)(value) if isinstance(current, Enum) else _frozen(value)
    for head, sub in nested.items():
        direct[head] = apply_overrides(getattr(obj, head), sub)
    return dataclasses.replace(obj, **direct)


def flatten_metrics(data: dict, prefix: str = "", drop: frozenset[str] | set[str] = frozenset()) -> dict:
    """Nested dict to ``{"a/b": value}``; lists and tuples become JSON strings."""
    out: dict = {}
    for key, value in data.items():
        if key in drop:
            continue
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten_metrics(value, f"{name}/"))
        elif isinstance(value, list | tuple):
            out[name] = json.dumps(value, default=float)
        elif hasattr(value, "item"):  # numpy scalar
            out[name] = value.item()
        else:
            out[name] = value
    return out


@dataclass(frozen=True)
class _EstimatorFactory:
    """``make_estimator`` with the sweep's MSCKF / window overrides applied to the settings it is given."""

    make: Callable[..., Any]
    msckf: dict
    window: dict

    def __call__(self, name, calib, noise, *, frontend="klt", params=None, window_params=None):
        from viotb.vio.msckf import MsckfParams  # noqa: PLC0415
        from viotb.vio.window import WindowParams  # noqa: PLC0415

        p = apply_overrides(params if params is not None else MsckfParams(), self.msckf)
        w = apply_overrides(window_params if window_params is not None else WindowParams(), self.window)
        return self.make(name, calib, noise, frontend=frontend, params=p, window_params=w)


@dataclass(frozen=True)
class _WithOverrides:
    """Wrap a function returning a frozen dataclass: the result gets ``fields`` replaced."""

    fn: Callable[..., Any]
    fields: dict

    def __call__(self, *args, **kwargs):
        return dataclasses.replace(self.fn(*args, **kwargs), **self.fields)


@dataclass(frozen=True)
class _RigSim:
    """``ClosedLoopSim`` built on its rig with the sweep's ``rig.*`` overrides applied."""

    cls: type
    overrides: dict

    def __call__(self, config, seed=0):
        return self.cls(apply_overrides(config, self.overrides), seed=seed)


def _record_eval(cfg: RunConfig, groups: dict[str, dict[str, Any]]) -> dict:
    from viotb.envs import evaluate, failures, record  # noqa: PLC0415

    if groups["rig"]:
        raise ValueError(f"rig.* parameters apply to mode 'fly' only, got {sorted(groups['rig'])}")
    with tempfile.TemporaryDirectory(prefix="viotb-sweep-") as tmp, ExitStack() as stack:
        if cfg.imu is not None:
            imu = {"imu_preset": cfg.imu}
            stack.enter_context(
                patch.object(record, "get_scenario", _WithOverrides(record.get_scenario, imu))
            )
            stack.enter_context(
                patch.object(
                    failures,
                    "failure_record_scenario",
                    _WithOverrides(failures.failure_record_scenario, imu),
                )
            )
        factory = _EstimatorFactory(evaluate.make_estimator, groups["msckf"], groups["window"])
        stack.enter_context(patch.object(evaluate, "make_estimator", factory))
        rec = record.record_scenario(
            cfg.scenario, tmp, seed=cfg.seed, seconds=cfg.seconds, severity=cfg.severity
        )
        opts = evaluate.EvalOptions(estimator=cfg.estimator, frontend=cfg.frontend, seed=cfg.seed)
        result = evaluate.evaluate_dataset(Path(tmp), Path(tmp) / "eval", opts)
    metrics = flatten_metrics(result, drop=_DROP["record-eval"])
    metrics.update(flatten_metrics(rec, "record/", drop=_DROP["record"]))
    return metrics


def _fly(cfg: RunConfig, groups: dict[str, dict[str, Any]]) -> dict:
    from viotb.envs import closed_loop  # noqa: PLC0415
    from viotb.envs import fly as fly_module  # noqa: PLC0415

    rig = dict(groups["rig"])
    if cfg.imu is not None:
        rig["imu_preset"] = cfg.imu
    with ExitStack() as stack:
        factory = _EstimatorFactory(closed_loop.make_estimator, groups["msckf"], groups["window"])
        stack.enter_context(patch.object(closed_loop, "make_estimator", factory))
        stack.enter_context(patch.object(fly_module, "ClosedLoopSim", _RigSim(fly_module.ClosedLoopSim, rig)))
        result, _log = fly_module.fly(
            cfg.scenario, cfg.estimator, cfg.seconds, cfg.seed, cfg.frontend, severity=cfg.severity
        )
    return flatten_metrics(result, drop=_DROP["fly"])


def _digest(data: dict) -> str:
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _frozen(value: Any) -> Any:
    """Lists to tuples, recursively (hashable, as frozen dataclass fields expect)."""
    if isinstance(value, list | tuple):
        return tuple(_frozen(v) for v in value)
    return value


def _jsonable(value: Any) -> Any:
    """Tuples to lists, recursively (for JSON and Parquet)."""
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value
