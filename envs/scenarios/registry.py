"""The one scenario registry: every open-loop, closed-loop and failure scenario is registered here only.

:func:`default_registry` builds it once, explicitly, from the libraries of this wing
(:mod:`~viotb.envs.scenarios.record_catalog`, :mod:`~viotb.envs.scenarios.head_catalog`,
:mod:`~viotb.envs.scenarios.fly_catalog`,
:mod:`~viotb.envs.scenarios.failures`); no module writes into another one at import time. Users add their own
scenarios with :func:`register` (open loop) or :func:`register_fly` (closed loop).
"""

from __future__ import annotations

import functools

from viotb.envs.scenarios.failures import FAILURES, failure_fly_scenarios, failure_record_scenario
from viotb.envs.scenarios.fly_catalog import fly_scenarios
from viotb.envs.scenarios.head_catalog import head_scenarios
from viotb.envs.scenarios.record_catalog import record_scenarios
from viotb.envs.scenarios.spec import SCENARIO_KINDS, FlyScenario, Scenario, listing

__all__ = [
    "SCENARIO_KINDS",
    "FlyScenario",
    "Scenario",
    "ScenarioRegistry",
    "default_registry",
    "fly_scenario_names",
    "get_fly_scenario",
    "get_scenario",
    "is_registered",
    "list_scenarios",
    "register",
    "register_fly",
]


class ScenarioRegistry:
    """Named scenarios: each as a :class:`Scenario` (the listing), closed-loop ones also as a FlyScenario.

    The :class:`FlyScenario` is what ``viotb fly`` runs.
    """

    def __init__(self) -> None:
        """An empty registry."""
        self._scenarios: dict[str, Scenario] = {}
        self._fly: dict[str, FlyScenario] = {}

    def register(self, scenario: Scenario, replace: bool = False) -> Scenario:
        """Add a scenario (ValueError on a duplicate name unless ``replace``)."""
        if scenario.name in self._scenarios and not replace:
            raise ValueError(f"scenario {scenario.name!r} is already registered")
        self._scenarios[scenario.name] = scenario
        return scenario

    def register_fly(self, scenario: FlyScenario, replace: bool = False) -> FlyScenario:
        """Add a closed-loop scenario, listed as a ``fly`` :class:`Scenario` (ValueError on a duplicate)."""
        self.register(listing(scenario), replace=replace)
        self._fly[scenario.name] = scenario
        return scenario

    def __contains__(self, name: object) -> bool:
        """Whether ``name`` is registered."""
        return name in self._scenarios

    def get(self, name: str) -> Scenario:
        """The scenario called ``name`` (ValueError listing the known names)."""
        try:
            return self._scenarios[name]
        except KeyError:
            known = ", ".join(sorted(self._scenarios))
            raise ValueError(f"unknown scenario {name!r}; known scenarios: {known}") from None

    def get_fly(self, name: str) -> FlyScenario:
        """The closed-loop scenario called ``name`` (ValueError listing the known ones)."""
        if name not in self._fly:
            raise ValueError(f"unknown closed-loop scenario {name!r}; known: {sorted(self._fly)}")
        return self._fly[name]

    def fly_names(self) -> list[str]:
        """Names of the closed-loop scenarios, sorted."""
        return sorted(self._fly)

    def listing(self) -> list[dict]:
        """All scenarios as dicts with keys name, kind, description, vehicle, scene, default_seconds."""
        return [
            {
                "name": s.name,
                "kind": s.kind,
                "description": s.description,
                "vehicle": s.vehicle,
                "scene": s.scene,
                "default_seconds": s.default_seconds,
            }
            for s in sorted(self._scenarios.values(), key=lambda s: (s.kind, s.name))
        ]


@functools.cache
def default_registry() -> ScenarioRegistry:
    """The registry of every scenario this package ships (built once per process, in this one place)."""
    reg = ScenarioRegistry()
    for sc in record_scenarios():
        reg.register(sc)
    for sc in head_scenarios():
        reg.register(sc)
    for name in FAILURES:
        reg.register(failure_record_scenario(name, 1.0))
    for fsc in fly_scenarios().values():
        reg.register_fly(fsc)
    for fsc in failure_fly_scenarios().values():
        reg.register_fly(fsc)
    return reg


def register(scenario: Scenario, replace: bool = False) -> Scenario:
    """Add a scenario to the default registry (ValueError on a duplicate name unless ``replace``)."""
    return default_registry().register(scenario, replace)


def register_fly(scenario: FlyScenario, replace: bool = False) -> FlyScenario:
    """Add a closed-loop scenario to the default registry."""
    return default_registry().register_fly(scenario, replace)


def is_registered(name: str) -> bool:
    """Whether ``name`` is in the default registry."""
    return name in default_registry()


def get_scenario(name: str) -> Scenario:
    """The scenario called ``name`` (ValueError listing the known names)."""
    return default_registry().get(name)


def get_fly_scenario(name: str) -> FlyScenario:
    """The closed-loop scenario called ``name`` (ValueError listing the known ones)."""
    return default_registry().get_fly(name)


def fly_scenario_names() -> list[str]:
    """Names of every closed-loop scenario, sorted."""
    return default_registry().fly_names()


def list_scenarios() -> list[dict]:
    """All scenarios as dicts with keys name, kind, description, vehicle, scene, default_seconds."""
    return default_registry().listing()
