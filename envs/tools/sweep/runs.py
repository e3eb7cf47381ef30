"""One run of a sweep: :class:`RunConfig` and :func:`run_config` (in this process, no Ray).

This is the only module of the sweep that imports the testbed's run functions (``viotb.envs.data.record``,
``viotb.envs.data.evaluate``, ``viotb.envs.run.fly``) and registries. The CLI imports it only when a sweep
runs, so ``viotb --help`` stays light.

Modes:

- ``record-eval``: :func:`record_scenario` into a temporary folder, then :func:`evaluate_dataset` on it (the
  ``viotb record`` + ``viotb eval`` pair); the metrics are the eval JSON, plus the recording's under
  ``record/``.
- ``fly``: :func:`fly` (``viotb fly``); the metrics are its JSON.

Parameter overrides are passed to the run functions as arguments: ``msckf.*`` / ``window.*`` as the
estimator settings of :class:`~viotb.envs.data.evaluate.EvalOptions` or of the rig
(:class:`~viotb.envs.sim.rig.RigConfig`), ``rig.*`` through ``fly(edit_rig=...)``, the ``imu`` axis as the
recording's or the rig's IMU preset.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tempfile
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from viotb.envs.data.evaluate import EvalOptions, evaluate_dataset
from viotb.envs.data.record import record_scenario
from viotb.envs.run.failure_runner import stream_metrics
from viotb.envs.run.fly import fly
from viotb.envs.scenarios.motions import TRAJECTORY_FACTORIES
from viotb.envs.scenarios.registry import list_scenarios
from viotb.envs.scenarios.streams import StreamConfig
from viotb.envs.sim.imu_model import imu_preset_names
from viotb.envs.sim.rig import RigConfig
from viotb.vio.factory import ESTIMATOR_NAMES, FRONTEND_NAMES
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.window import WindowParams

MODES = ("record-eval", "fly", "stream")
"""Run modes: record then evaluate (open loop), a closed-loop flight, or an in-memory stream (no rendering:
``viotb regress``'s open-loop cases; the scenario is a motion of the library)."""
CORE_AXES = ("mode", "scenario", "estimator", "frontend", "imu", "severity", "seconds")
"""Axes of a run besides the seed and the dataclass parameters."""
PARAM_ROOTS = ("msckf", "window", "rig", "stream")
"""Prefixes of parameter axes: ``msckf.<MsckfParams field>``, ``window.<WindowParams field>``,
``rig.<RigConfig field>``, ``stream.<StreamConfig field>`` (nested dataclasses by more dots:
``msckf.klt.max_features``)."""
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
    items = list_scenarios()
    kinds = {"record-eval": "record", "fly": "fly"}
    scenarios = {mode: tuple(s["name"] for s in items if s["kind"] == kind) for mode, kind in kinds.items()}
    scenarios["stream"] = tuple(sorted(TRAJECTORY_FACTORIES))
    return Catalog(
        scenarios=scenarios,
        estimators=tuple(ESTIMATOR_NAMES),
        frontends=tuple(FRONTEND_NAMES),
        imu_presets=tuple(imu_preset_names()),
        param_roots={"msckf": MsckfParams, "window": WindowParams, "rig": RigConfig, "stream": StreamConfig},
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
    from threadpoolctl import threadpool_limits

    os.environ.setdefault("MUJOCO_GL", "egl")
    groups = split_params(cfg.params)
    with threadpool_limits(1):
        if cfg.mode == "record-eval":
            return _record_eval(cfg, groups)
        if cfg.mode == "fly":
            return _fly(cfg, groups)
        if cfg.mode == "stream":
            return _stream(cfg, groups)
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
class _RigEdit:
    """Picklable rig edit of a ``fly`` run: ``rig.*`` fields, the IMU axis and the estimator settings."""

    rig: dict
    msckf: dict
    window: dict

    def __call__(self, rig: RigConfig) -> RigConfig:
        rig = apply_overrides(rig, self.rig)
        msckf = apply_overrides(rig.msckf if rig.msckf is not None else MsckfParams(), self.msckf)
        window = apply_overrides(rig.window if rig.window is not None else WindowParams(), self.window)
        return dataclasses.replace(rig, msckf=msckf, window=window)


def _record_eval(cfg: RunConfig, groups: dict[str, dict[str, Any]]) -> dict:
    if groups["rig"]:
        raise ValueError(f"rig.* parameters apply to mode 'fly' only, got {sorted(groups['rig'])}")
    with tempfile.TemporaryDirectory(prefix="viotb-sweep-") as tmp:
        rec = record_scenario(
            cfg.scenario, tmp, seed=cfg.seed, seconds=cfg.seconds, severity=cfg.severity, imu_preset=cfg.imu
        )
        opts = EvalOptions(
            estimator=cfg.estimator,
            frontend=cfg.frontend,
            seed=cfg.seed,
            msckf=apply_overrides(MsckfParams(), groups["msckf"]),
            window=apply_overrides(WindowParams(), groups["window"]),
        )
        result = evaluate_dataset(Path(tmp), Path(tmp) / "eval", opts)
    metrics = flatten_metrics(result, drop=_DROP["record-eval"])
    metrics.update(flatten_metrics(rec, "record/", drop=_DROP["record"]))
    return metrics


def _fly(cfg: RunConfig, groups: dict[str, dict[str, Any]]) -> dict:
    rig = dict(groups["rig"])
    if cfg.imu is not None:
        rig["imu_preset"] = cfg.imu
    result, _log = fly(
        cfg.scenario,
        cfg.estimator,
        cfg.seconds,
        cfg.seed,
        cfg.frontend,
        severity=cfg.severity,
        edit_rig=_RigEdit(rig, groups["msckf"], groups["window"]),
    )
    return flatten_metrics(result, drop=_DROP["fly"])


def _stream(cfg: RunConfig, groups: dict[str, dict[str, Any]]) -> dict:
    """An in-memory stream of motion ``cfg.scenario`` through the MSCKF or the window optimizer."""
    if groups["rig"] or groups["window"]:
        raise ValueError(f"mode 'stream' takes msckf.* and stream.* parameters, got {cfg.params}")
    sc = StreamConfig(motion=cfg.scenario)
    if cfg.seconds is not None:
        sc = dataclasses.replace(sc, seconds=float(cfg.seconds))
    if cfg.imu is not None:
        sc = dataclasses.replace(sc, imu_preset=cfg.imu)
    sc = apply_overrides(sc, groups["stream"])
    params = apply_overrides(MsckfParams(), groups["msckf"])
    return flatten_metrics(stream_metrics(sc, cfg.seed, params, estimator=cfg.estimator))


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
