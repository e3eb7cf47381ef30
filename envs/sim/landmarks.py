"""Scene landmarks and their projection, for the simulated-feature fast mode (no rendering).

:func:`scene_landmarks` draws 3-D points on the visible textured surfaces of a compiled scene (the world
body's plane and box geoms whose material has a texture: floor, walls, posters, crates, pillars, but not
the untextured walls of ``blank_wall``). :func:`project_landmarks` turns them into the measurements a
feature tracker would report (open_vins ``TrackSIM`` idea): ids plus distorted, noisy pixels of the points
in front of the camera and inside the image, optionally minus the ones hidden behind scene geometry.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from viotb.vio.camera import PinholeCamera
from viotb.vio.types import FeatureObservations

SURFACE_OFFSET_M = 0.01
"""A surface point is visible when the point this far along its outward normal is in free space (m)."""

_OCCLUSION_TOL_M = 0.01
"""A ray that first hits scene geometry within this distance of the landmark counts as reaching it (m)."""

_SCENE_GEOM_GROUPS = np.array([1, 1, 0, 0, 0, 0], dtype=np.uint8)
"""Geom groups the occlusion rays test: 0 and 1 (scene); vehicles use groups 2 (visual) and 3 (collision)."""

_FOV_MARGIN = 0.5
"""Points whose undistorted projection lies beyond the image by more than this fraction are dropped
before distortion (the polynomial can fold far-off points back into the image)."""


@dataclass(frozen=True)
class _Rectangle:
    """A planar rectangle in W: ``centre + u axis_u + v axis_v``, ``|u| <= half_u``, ``|v| <= half_v``."""

    centre_W: np.ndarray
    axis_u_W: np.ndarray
    axis_v_W: np.ndarray
    normal_W: np.ndarray
    half_u_m: float
    half_v_m: float

    @property
    def area_m2(self) -> float:
        """Area (m^2)."""
        return 4.0 * self.half_u_m * self.half_v_m


def _world_geoms(model: mujoco.MjModel, geom_type: mujoco.mjtGeom) -> np.ndarray:
    """Ids of the world body's geoms of one type."""
    return np.flatnonzero((model.geom_bodyid == 0) & (model.geom_type == geom_type))


def _is_textured(model: mujoco.MjModel, geom_id: int) -> bool:
    """True when the geom's material has an RGB texture."""
    mat_id = int(model.geom_matid[geom_id])
    return mat_id >= 0 and int(model.mat_texid[mat_id, int(mujoco.mjtTextureRole.mjTEXROLE_RGB)]) >= 0


def _geom_rectangles(model: mujoco.MjModel, data: mujoco.MjData, geom_id: int) -> list[_Rectangle]:
    """Visible-side rectangles of a plane (its +z face) or a box (its six faces), in W."""
    R = data.geom_xmat[geom_id].reshape(3, 3)
    centre = data.geom_xpos[geom_id]
    size = model.geom_size[geom_id]
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, geom_id)
    if model.geom_type[geom_id] == mujoco.mjtGeom.mjGEOM_PLANE:
        if size[0] <= 0 or size[1] <= 0:
            raise ValueError(f"geom {name!r}: landmarks need a finite plane, got size {size[:2].tolist()}")
        return [_Rectangle(centre.copy(), R[:, 0], R[:, 1], R[:, 2], float(size[0]), float(size[1]))]
    rects = []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for sign in (1.0, -1.0):
            rects.append(
                _Rectangle(
                    centre + sign * size[axis] * R[:, axis],
                    R[:, u],
                    R[:, v],
                    sign * R[:, axis],
                    float(size[u]),
                    float(size[v]),
                )
            )
    return rects


def _inside_solid(model: mujoco.MjModel, data: mujoco.MjData, points_W: np.ndarray) -> np.ndarray:
    """Mask of points inside the scene's solids: behind a plane (half-space) or inside a box, shape (N,)."""
    inside = np.zeros(len(points_W), dtype=bool)
    for g in _world_geoms(model, mujoco.mjtGeom.mjGEOM_PLANE):
        R = data.geom_xmat[g].reshape(3, 3)
        local = (points_W - data.geom_xpos[g]) @ R
        size = model.geom_size[g]
        within = (np.abs(local[:, 0]) <= size[0]) & (np.abs(local[:, 1]) <= size[1])
        inside |= within & (local[:, 2] < 0.0) & (local[:, 2] > -1.0)
    for g in _world_geoms(model, mujoco.mjtGeom.mjGEOM_BOX):
        R = data.geom_xmat[g].reshape(3, 3)
        local = (points_W - data.geom_xpos[g]) @ R
        inside |= np.all(np.abs(local) < model.geom_size[g], axis=1)
    return inside


def scene_landmarks(model: mujoco.MjModel, rng: np.random.Generator, count: int = 3000) -> np.ndarray:
    """Points spread uniformly (by area) over the visible textured surfaces of the scene.

    Surfaces are the +z side of the world body's textured planes and the faces of its textured boxes; a
    point is kept when the point ``SURFACE_OFFSET_M`` along the outward normal is not inside another
    solid (so crate bottoms, wall areas under posters and the hidden faces of stacked pillar segments get
    none).

    Args:
        model: A compiled model (scene plus vehicle; only the world body's geoms are used).
        rng: Random generator.
        count: Number of landmarks (> 0).

    Returns:
        Landmark positions in W (m), shape (count, 3).

    Raises:
        ValueError: ``count <= 0``, or the scene has no textured surface (e.g. ``empty``).
    """
    if count <= 0:
        raise ValueError(f"count must be positive, got {count}")
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    rects: list[_Rectangle] = []
    for geom_type in (mujoco.mjtGeom.mjGEOM_PLANE, mujoco.mjtGeom.mjGEOM_BOX):
        for g in _world_geoms(model, geom_type):
            if _is_textured(model, int(g)):
                rects.extend(_geom_rectangles(model, data, int(g)))
    if not rects:
        raise ValueError("scene has no textured plane or box surface to put landmarks on")
    area = np.array([r.area_m2 for r in rects])
    centre = np.array([r.centre_W for r in rects])
    axis_u = np.array([r.axis_u_W for r in rects])
    axis_v = np.array([r.axis_v_W for r in rects])
    normal = np.array([r.normal_W for r in rects])
    half = np.array([[r.half_u_m, r.half_v_m] for r in rects])
    points: list[np.ndarray] = []
    n_found = 0
    for _ in range(100):
        batch = 2 * (count - n_found) + 16
        k = rng.choice(len(rects), size=batch, p=area / area.sum())
        uv = rng.uniform(-1.0, 1.0, size=(batch, 2)) * half[k]
        p = centre[k] + uv[:, :1] * axis_u[k] + uv[:, 1:] * axis_v[k]
        keep = ~_inside_solid(model, data, p + SURFACE_OFFSET_M * normal[k])
        points.append(p[keep])
        n_found += int(keep.sum())
        if n_found >= count:
            return np.concatenate(points)[:count]
    raise ValueError(f"could not place {count} landmarks on visible surfaces (found {n_found})")


def _unoccluded(
    model: mujoco.MjModel, data: mujoco.MjData, p_WC: np.ndarray, points_W: np.ndarray
) -> np.ndarray:
    """Mask of points whose ray from the camera centre reaches them before any scene geom, shape (N,)."""
    if len(points_W) == 0:
        return np.zeros(0, dtype=bool)
    vec = points_W - p_WC
    dist_m = np.linalg.norm(vec, axis=1)
    dirs = vec / dist_m[:, None]
    geom_id = np.zeros(len(points_W), dtype=np.int32)
    hit_m = np.zeros(len(points_W))
    mujoco.mj_multiRay(
        model,
        data,
        np.asarray(p_WC, dtype=float),
        dirs.ravel(),
        _SCENE_GEOM_GROUPS,
        1,
        -1,
        geom_id,
        hit_m,
        None,
        len(points_W),
        float(dist_m.max()) + 1.0,
    )
    return (hit_m < 0) | (hit_m >= dist_m - _OCCLUSION_TOL_M)


def project_landmarks(
    landmarks_W: np.ndarray,
    R_WC: np.ndarray,
    p_WC: np.ndarray,
    camera: PinholeCamera,
    rng: np.random.Generator,
    pixel_sigma_px: float = 0.5,
    max_depth_m: float = 20.0,
    model: mujoco.MjModel | None = None,
    data: mujoco.MjData | None = None,
) -> FeatureObservations:
    """Measurements of the landmarks seen by a camera.

    Steps: (1) transform to the camera frame ``p_C = R_WC^T (p_W - p_WC)``; (2) keep ``0 < z <= max_depth_m``
    and undistorted projections near the image; (3) optionally drop points hidden behind scene geometry
    (``mujoco.mj_multiRay`` from the camera centre; needs ``model`` and ``data`` after ``mj_forward``);
    (4) distort and project with ``camera``, add Gaussian pixel noise; (5) keep the noisy pixels inside the
    image.

    Args:
        landmarks_W: Landmark positions in W (m), shape (N, 3); the id of a landmark is its row.
        R_WC: Camera orientation (OpenCV convention), shape (3, 3).
        p_WC: Camera centre in W (m), shape (3,).
        camera: Intrinsics and distortion.
        rng: Random generator for the pixel noise.
        pixel_sigma_px: Standard deviation of the pixel noise per axis (px), >= 0.
        max_depth_m: Farthest visible depth along the optical axis (m).
        model: Optional model for the occlusion test (together with ``data``).
        data: Optional data for the occlusion test.

    Returns:
        Observations with ids (M,) int64 (ascending) and distorted noisy pixels (M, 2).

    Raises:
        ValueError: Bad shapes, a negative sigma, a non-positive depth, or only one of ``model``/``data``.
    """
    landmarks_W = np.asarray(landmarks_W, dtype=float)
    if landmarks_W.ndim != 2 or landmarks_W.shape[1] != 3:
        raise ValueError(f"landmarks_W must have shape (N, 3), got {landmarks_W.shape}")
    R_WC = np.asarray(R_WC, dtype=float)
    p_WC = np.asarray(p_WC, dtype=float)
    if R_WC.shape != (3, 3) or p_WC.shape != (3,):
        raise ValueError(f"R_WC must be (3, 3) and p_WC (3,), got {R_WC.shape} and {p_WC.shape}")
    if pixel_sigma_px < 0:
        raise ValueError(f"pixel_sigma_px must be >= 0, got {pixel_sigma_px}")
    if max_depth_m <= 0:
        raise ValueError(f"max_depth_m must be positive, got {max_depth_m}")
    if (model is None) != (data is None):
        raise ValueError("the occlusion test needs both model and data (or neither)")
    # 1. Camera frame (row form of R_WC^T (p_W - p_WC)).
    p_C = (landmarks_W - p_WC) @ R_WC
    # 2. In front, within range, and (undistorted) near the image.
    z = p_C[:, 2]
    ids = np.flatnonzero((z > 1e-6) & (z <= max_depth_m))
    xy = p_C[ids, :2] / z[ids, None]
    u = camera.fx * xy[:, 0] + camera.cx
    v = camera.fy * xy[:, 1] + camera.cy
    mu, mv = _FOV_MARGIN * camera.width, _FOV_MARGIN * camera.height
    near = (u > -mu) & (u < camera.width + mu) & (v > -mv) & (v < camera.height + mv)
    ids, xy = ids[near], xy[near]
    # 3. Occlusion by scene geometry.
    if model is not None:
        visible = _unoccluded(model, data, p_WC, landmarks_W[ids])
        ids, xy = ids[visible], xy[visible]
    # 4. Distort, project, add noise.
    uv_px = camera.normalized_to_pixels(xy)
    if pixel_sigma_px > 0:
        uv_px = uv_px + rng.normal(0.0, pixel_sigma_px, size=uv_px.shape)
    # 5. Inside the image.
    inside = camera.in_image(uv_px)
    return FeatureObservations(ids=ids[inside].astype(np.int64), uv_px=uv_px[inside])
