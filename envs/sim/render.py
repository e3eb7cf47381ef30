"""Offscreen rendering and the MuJoCo-camera to OpenCV-camera conversion (the only place doing either).

MuJoCo cameras look along their -z axis with y up; OpenCV cameras look along +z with y down. The two
frames differ by a rotation of pi about x::

    R_BC = R_B_Cmujoco @ diag(1, -1, -1)

Intrinsics of a MuJoCo camera of vertical field of view ``fovy`` rendered at ``width x height`` (square
pixels, pixel centres at integer coordinates)::

    fx = fy = (height / 2) / tan(fovy / 2),   cx = width / 2 - 0.5,   cy = height / 2 - 0.5

``mujoco.Renderer`` already returns rows from top to bottom, so no flip is needed.
"""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Callable

import numpy as np
from viotb.vio.camera import CameraCalibration, PinholeCamera

EGL_PACKAGES = "libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1 libopengl0"
"""Debian packages that provide headless EGL rendering (Mesa)."""
OSMESA_PACKAGES = "libosmesa6"
"""Debian package that provides OSMesa software rendering (plus the ``pyopengl`` Python package)."""

_R_CMUJOCO_COPENCV = np.diag([1.0, -1.0, -1.0])
"""Rotation OpenCV camera frame -> MuJoCo camera frame (pi about x); it is its own inverse."""

GRAY_WEIGHTS = np.array([0.299, 0.587, 0.114])
"""ITU-R BT.601 luma weights for RGB -> gray (the weights OpenCV's cvtColor uses)."""
_GRAY_WEIGHTS_F32 = GRAY_WEIGHTS.astype(np.float32)


def _egl_available() -> bool:
    """True when an EGL context can be created (probes by making and freeing one)."""
    try:
        from mujoco.egl import GLContext  # (import selects the backend)

        ctx = GLContext(16, 16)
        ctx.make_current()
        ctx.free()
    except Exception:  # noqa: BLE001 (any failure means "not available")
        return False
    return True


def _osmesa_available() -> bool:
    """True when OSMesa can be loaded (pyopengl installed and libOSMesa present)."""
    if importlib.util.find_spec("OpenGL") is None:
        return False
    try:
        from mujoco.osmesa import GLContext

        ctx = GLContext(16, 16)
        ctx.make_current()
        ctx.free()
    except Exception:  # noqa: BLE001
        return False
    return True


def _bind_mujoco_context(backend: str) -> None:
    """Point MuJoCo's renderer at ``backend``'s GLContext.

    ``import mujoco`` binds ``GLContext`` from ``MUJOCO_GL`` once, at import time (glfw when unset, which
    fails headless). When mujoco was imported before the backend was chosen, rebind it here; the renderer
    reads ``mujoco.rendering.classic.gl_context.GLContext`` each time it creates a context.
    """
    import sys

    module = sys.modules.get("mujoco.rendering.classic.gl_context")
    if module is None:
        return
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    else:
        return
    module.GLContext = GLContext


def select_gl_backend(
    egl_probe: Callable[[], bool] | None = None, osmesa_probe: Callable[[], bool] | None = None
) -> str:
    """Choose the offscreen OpenGL backend and export it in ``MUJOCO_GL`` (and ``PYOPENGL_PLATFORM``).

    Must run before MuJoCo creates its first rendering context. An explicit ``MUJOCO_GL`` in the
    environment is honoured as is; otherwise EGL is tried first, then OSMesa.

    Args:
        egl_probe: Returns True when EGL works (default: create a tiny EGL context). For tests.
        osmesa_probe: Returns True when OSMesa works (default: create a tiny OSMesa context). For tests.

    Returns:
        The backend name: ``"egl"``, ``"osmesa"`` or the explicit ``MUJOCO_GL`` value.

    Raises:
        RuntimeError: Neither backend works; the message names the Debian packages to install.
    """
    explicit = os.environ.get("MUJOCO_GL")
    if explicit:
        _bind_mujoco_context(explicit.lower().strip())
        return explicit
    os.environ["MUJOCO_GL"] = "egl"
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    if (egl_probe or _egl_available)():
        _bind_mujoco_context("egl")
        return "egl"
    os.environ["MUJOCO_GL"] = "osmesa"
    os.environ["PYOPENGL_PLATFORM"] = "osmesa"
    if (osmesa_probe or _osmesa_available)():
        _bind_mujoco_context("osmesa")
        return "osmesa"
    del os.environ["MUJOCO_GL"]
    del os.environ["PYOPENGL_PLATFORM"]
    raise RuntimeError(
        "no offscreen OpenGL backend for MuJoCo: EGL failed (install the Debian packages "
        f"`{EGL_PACKAGES}`) and OSMesa failed (install `{OSMESA_PACKAGES}` and `pip install pyopengl`); "
        "or set MUJOCO_GL explicitly"
    )


def _camera_id(model, camera_name: str) -> int:
    """Id of a named camera, with a clear error listing the model's cameras."""
    import mujoco  # (after select_gl_backend)

    cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera_name)
    if cam_id < 0:
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(model.ncam)]
        raise ValueError(f"camera {camera_name!r} not in model; cameras: {names}")
    return cam_id


def camera_intrinsics(model, camera_name: str, width: int, height: int) -> PinholeCamera:
    """Pinhole intrinsics of a MuJoCo camera rendered at ``width x height`` (from its ``fovy``).

    Raises:
        ValueError: Unknown camera, or a non-positive image size.
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got width={width}, height={height}")
    cam_id = _camera_id(model, camera_name)
    return PinholeCamera.from_fovy(width, height, float(model.cam_fovy[cam_id]))


def camera_extrinsics(model, camera_name: str, body_name: str) -> tuple[np.ndarray, np.ndarray]:
    """Pose of the OpenCV camera frame C in the frame of ``body_name`` (the camera's parent body).

    Returns:
        ``(R_BC (3, 3), p_BC (3,) m)`` with ``R_BC = R_B_Cmujoco @ diag(1, -1, -1)``.

    Raises:
        ValueError: Unknown camera or body, or the camera is not attached to that body.
    """
    import mujoco

    cam_id = _camera_id(model, camera_name)
    body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body_name)
    if body_id < 0:
        raise ValueError(f"body {body_name!r} not in model")
    if int(model.cam_bodyid[cam_id]) != body_id:
        raise ValueError(f"camera {camera_name!r} is not attached to body {body_name!r}")
    R_B_Cmujoco = np.empty(9)
    mujoco.mju_quat2Mat(R_B_Cmujoco, model.cam_quat[cam_id])
    R_BC = R_B_Cmujoco.reshape(3, 3) @ _R_CMUJOCO_COPENCV
    return R_BC, model.cam_pos[cam_id].copy()


def camera_world_pose(data, cam_id: int) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV camera pose in W from MuJoCo's ``cam_xmat``/``cam_xpos`` (after ``mj_forward``).

    Returns:
        ``(R_WC (3, 3), p_WC (3,) m)``.
    """
    R_W_Cmujoco = data.cam_xmat[cam_id].reshape(3, 3)
    return R_W_Cmujoco @ _R_CMUJOCO_COPENCV, data.cam_xpos[cam_id].copy()


MAX_OFFSCREEN_PX = 4096
"""Largest offscreen buffer side (px) :func:`ensure_offscreen_buffer` grows a model to."""


def ensure_offscreen_buffer(model, width: int, height: int) -> None:
    """Grow the model's offscreen buffer (``<global offwidth/offheight>``) to hold ``width`` x ``height``.

    MuJoCo sizes its offscreen framebuffer from these fields when a renderer is created; the MJCF default
    here is 752x480 (EuRoC's size). Call before creating an :class:`OffscreenRenderer` for a larger image.

    Raises:
        ValueError: A side that is not a positive integer or exceeds :data:`MAX_OFFSCREEN_PX`.
    """
    for what, value in (("width", width), ("height", height)):
        if not (isinstance(value, int | np.integer) and 0 < value <= MAX_OFFSCREEN_PX):
            raise ValueError(f"image {what} must be an integer in [1, {MAX_OFFSCREEN_PX}] px, got {value!r}")
    model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), int(width))
    model.vis.global_.offheight = max(int(model.vis.global_.offheight), int(height))


def camera_calibration(
    model,
    camera_name: str,
    body_name: str,
    width: int,
    height: int,
    time_offset_s: float = 0.0,
    rate_hz: float = 20.0,
) -> CameraCalibration:
    """Intrinsics plus camera-body extrinsics of a MuJoCo camera (B = body = IMU frame)."""
    R_BC, p_BC = camera_extrinsics(model, camera_name, body_name)
    return CameraCalibration(
        camera=camera_intrinsics(model, camera_name, width, height),
        R_BC=R_BC,
        p_BC=p_BC,
        time_offset_s=float(time_offset_s),
        rate_hz=float(rate_hz),
    )


def rgb_to_gray(rgb: np.ndarray) -> np.ndarray:
    """RGB uint8 ``(H, W, 3)`` -> gray float64 ``(H, W)`` in [0, 255] (BT.601 weights)."""
    return rgb.astype(np.float32) @ _GRAY_WEIGHTS_F32


class SceneLights:
    """Switches every light of a model (its lamps and the camera headlight) off and back on.

    With all of them off the render is black (the scenes' materials emit nothing): the lights-out scenarios
    use it to darken the room mid-flight. The model's own values are restored when switched back on.

    Args:
        model: The ``mujoco.MjModel`` (edited in place).
    """

    def __init__(self, model) -> None:
        """Remember the model's lighting; the lights start on."""
        self._model = model
        self._light_active = np.array(model.light_active, copy=True)
        head = model.vis.headlight
        self._head = (head.ambient.copy(), head.diffuse.copy(), head.specular.copy())
        self.on = True

    def set_on(self, on: bool) -> None:
        """Switch the lights on (the model's values) or off (lamps inactive, headlight black)."""
        if bool(on) == self.on:
            return
        head = self._model.vis.headlight
        for field, saved in zip((head.ambient, head.diffuse, head.specular), self._head, strict=True):
            field[:] = saved if on else 0.0
        self._model.light_active[:] = self._light_active if on else False
        self.on = bool(on)


class OffscreenRenderer:
    """Renders a model's camera offscreen into numpy images (``mujoco.Renderer`` underneath).

    Args:
        model: The ``mujoco.MjModel``.
        width: Image width (px); at most the model's ``offwidth``.
        height: Image height (px); at most the model's ``offheight``.
        camera: Camera name rendered by :meth:`render_gray` and :meth:`render_depth`.
        pixel_noise_std: Standard deviation of additive Gaussian pixel noise (gray levels) in
            :meth:`render_gray`; needs ``rng`` when positive.
        rng: Random generator for the pixel noise.

    Raises:
        ValueError: Unknown camera, size larger than the offscreen buffer, negative noise, or noise
            without an ``rng``.
    """

    def __init__(
        self,
        model,
        width: int = 320,
        height: int = 240,
        camera: str | None = None,
        pixel_noise_std: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> None:
        """Create the GL context and the renderer (selects the GL backend first)."""
        from viotb.models.constants import ONBOARD_CAMERA

        select_gl_backend()
        import mujoco

        camera = ONBOARD_CAMERA if camera is None else camera
        if width > model.vis.global_.offwidth or height > model.vis.global_.offheight:
            raise ValueError(
                f"image {width}x{height} exceeds the model's offscreen buffer "
                f"{model.vis.global_.offwidth}x{model.vis.global_.offheight} (<global offwidth/offheight>)"
            )
        if pixel_noise_std < 0:
            raise ValueError(f"pixel_noise_std must be >= 0, got {pixel_noise_std}")
        if pixel_noise_std > 0 and rng is None:
            raise ValueError("pixel_noise_std > 0 needs an rng (numpy.random.Generator)")
        self._camera_name = camera
        self._cam_id = _camera_id(model, camera)
        self._camera = camera_intrinsics(model, camera, width, height)
        self._model = model
        self._noise_std = float(pixel_noise_std)
        self._rng = rng
        # The context allocates its offscreen framebuffer (with the MSAA samples) at the model's offwidth x
        # offheight; one of the image's own size renders the same pixels (tested) with less to clear and to
        # resolve per frame (4-8 % of a 320x240 frame's CPU on llvmpipe). The model keeps its sizes.
        vis = model.vis.global_
        full_size = (vis.offwidth, vis.offheight)
        vis.offwidth, vis.offheight = width, height
        try:
            self._renderer = mujoco.Renderer(model, height=height, width=width)
        finally:
            vis.offwidth, vis.offheight = full_size
        self._depth_on = False
        self._buffers: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def camera(self) -> PinholeCamera:
        """Intrinsics of the rendered camera at this renderer's size."""
        return self._camera

    def render_rgb(self, data, camera: str | None = None) -> np.ndarray:
        """Render ``camera`` (default: this renderer's camera) as RGB uint8, shape (H, W, 3)."""
        if self._depth_on:
            self._renderer.disable_depth_rendering()
            self._depth_on = False
        cam = self._cam_id if camera is None else _camera_id(self._model, camera)
        self._renderer.update_scene(data, camera=cam)
        return self._renderer.render()

    def render_gray(self, data) -> np.ndarray:
        """Render this renderer's camera as gray uint8, shape (H, W), with optional Gaussian noise.

        The RGB, float and gray intermediates live in buffers reused from frame to frame (the same
        operations as :func:`rgb_to_gray`, so the same image); only the returned image is new.
        """
        if self._buffers is None:
            h, w = self._camera.height, self._camera.width
            self._buffers = (
                np.empty((h, w, 3), np.uint8),
                np.empty((h, w, 3), np.float32),
                np.empty((h, w), np.float32),
            )
        rgb, rgb_f32, gray = self._buffers
        if self._depth_on:
            self._renderer.disable_depth_rendering()
            self._depth_on = False
        self._renderer.update_scene(data, camera=self._cam_id)
        self._renderer.render(out=rgb)
        np.copyto(rgb_f32, rgb)
        np.matmul(rgb_f32, _GRAY_WEIGHTS_F32, out=gray)
        return self._to_uint8(gray)

    def render_gray_exposure(self, data, place: Callable[[float], None], offsets_s: np.ndarray) -> np.ndarray:
        """Gray uint8 image integrated over an exposure (motion blur), shape (H, W).

        The mean of one render per offset, each after ``place(offset)`` has moved the scene in ``data`` to
        that time within the exposure; the sensor noise is added once, to the integrated image.

        Args:
            data: ``MjData`` that ``place`` updates.
            place: Sets ``data`` to the state at the given offset (s) from the exposure centre.
            offsets_s: Offsets (s) of the renders, shape (N,), N >= 1.
        """
        acc = None
        for offset in np.asarray(offsets_s, dtype=float):
            place(float(offset))
            rgb = self.render_rgb(data).astype(np.float32)
            acc = rgb if acc is None else acc + rgb
        if acc is None:
            raise ValueError("render_gray_exposure: offsets_s is empty")
        return self._to_uint8(rgb_to_gray(acc / len(offsets_s)))

    def _to_uint8(self, gray: np.ndarray) -> np.ndarray:
        """Add the sensor noise and quantize to uint8."""
        if self._noise_std > 0:
            gray = gray + self._rng.normal(0.0, self._noise_std, size=gray.shape).astype(np.float32)
        return np.clip(np.rint(gray), 0, 255).astype(np.uint8)

    def render_depth(self, data) -> np.ndarray:
        """Render this renderer's camera as metric depth along the optical axis (m), shape (H, W)."""
        if not self._depth_on:
            self._renderer.enable_depth_rendering()
            self._depth_on = True
        self._renderer.update_scene(data, camera=self._cam_id)
        return self._renderer.render().astype(np.float64)

    def close(self) -> None:
        """Free the GL context."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> OffscreenRenderer:
        """Context-manager entry."""
        return self

    def __exit__(self, *exc) -> None:
        """Context-manager exit: :meth:`close`."""
        self.close()
