"""MJCF models: quadrotor, headset rig and scenes, composed by :func:`load_model`."""

from __future__ import annotations

import mujoco
from viotb.models.constants import MODELS_DIR, SCENE_XMLS, VEHICLE_XMLS


def compose_xml(vehicle: str, scene: str) -> str:
    """MJCF text that includes a scene file and a vehicle file.

    Raises:
        ValueError: Unknown vehicle or scene name (the message lists the known names).
    """
    if vehicle not in VEHICLE_XMLS:
        raise ValueError(f"unknown vehicle {vehicle!r}; known: {sorted(VEHICLE_XMLS)}")
    if scene not in SCENE_XMLS:
        raise ValueError(f"unknown scene {scene!r}; known: {sorted(SCENE_XMLS)}")
    return (
        f'<mujoco model="{vehicle}_{scene}">'
        f'<include file="{SCENE_XMLS[scene]}"/><include file="{VEHICLE_XMLS[vehicle]}"/>'
        "</mujoco>"
    )


def load_model(vehicle: str = "quadrotor", scene: str = "empty") -> mujoco.MjModel:
    """Compile ``vehicle`` placed in ``scene`` (both names from :mod:`viotb.models.constants`)."""
    xml = compose_xml(vehicle, scene)
    return mujoco.MjModel.from_xml_string(xml, _assets())


def _assets() -> dict[str, bytes]:
    """Every file under the models folder, keyed by its path relative to it (MuJoCo's VFS)."""
    return {
        str(p.relative_to(MODELS_DIR)): p.read_bytes()
        for p in MODELS_DIR.rglob("*")
        if p.is_file() and p.suffix in {".xml", ".png"}
    }
