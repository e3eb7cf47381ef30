"""The rig's cameras together: one calibration and one offscreen renderer per camera (mono or stereo).

A stereo rig renders both cameras at the same exposure instants (global shutter, hardware-synchronised as
headset tracking cameras are); each camera has its own pixel-noise stream so that adding ``cam1`` leaves the
``cam0`` images of a seed unchanged.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from viotb.envs.sim.camera_timing import CameraModelParams
from viotb.envs.sim.render import OffscreenRenderer, camera_calibration
from viotb.vio.camera import CameraCalibration


class CameraRig:
    """Calibrations and renderers of the named cameras of one model (left = ``cam0`` first).

    Args:
        model: The compiled ``mujoco.MjModel`` (scene plus vehicle).
        camera_names: MuJoCo camera names, 1 or 2.
        body_name: The vehicle body (B = IMU frame) the cameras are attached to.
        params: Resolution, rate, clock offset, pixel noise and exposure (shared by the cameras).
        rngs: One pixel-noise generator per camera.
        render: Create the renderers (False: calibrations only, e.g. for the simulated-feature front end).
    """

    def __init__(
        self,
        model,
        camera_names: Sequence[str],
        body_name: str,
        params: CameraModelParams,
        rngs: Sequence[np.random.Generator],
        render: bool = True,
    ) -> None:
        """Build the calibrations (and renderers)."""
        if len(camera_names) not in (1, 2) or len(rngs) < len(camera_names):
            raise ValueError(f"CameraRig: 1 or 2 cameras with one rng each, got {list(camera_names)}")
        self.names = tuple(camera_names)
        self.params = params
        self.calibs: list[CameraCalibration] = [
            camera_calibration(
                model, name, body_name, params.width, params.height, params.time_offset_s, params.rate_hz
            )
            for name in self.names
        ]
        self.renderers: list[OffscreenRenderer] = []
        if render:
            for name, rng in zip(self.names, rngs, strict=False):
                self.renderers.append(
                    OffscreenRenderer(model, params.width, params.height, name, params.pixel_noise_std, rng)
                )
        self._blur_offsets_s = np.linspace(-0.5, 0.5, params.blur_samples) * params.exposure_s

    def __len__(self) -> int:
        """Number of cameras."""
        return len(self.names)

    def render(self, data, place: Callable[[float], None], t_exposure_s: float) -> list[np.ndarray]:
        """Gray uint8 images (H, W) of every camera, exposed around ``t_exposure_s`` (s).

        Args:
            data: ``MjData`` that ``place`` updates.
            place: Puts the vehicle at a time (s) in ``data`` (kinematically).
            t_exposure_s: Centre of the exposure (IMU clock).
        """
        images = []
        for renderer in self.renderers:
            if self.params.exposure_s > 0.0:
                images.append(
                    renderer.render_gray_exposure(
                        data, lambda o, t=t_exposure_s: place(t + o), self._blur_offsets_s
                    )
                )
            else:
                place(t_exposure_s)
                images.append(renderer.render_gray(data))
        return images

    def close(self) -> None:
        """Free the GL contexts."""
        for renderer in self.renderers:
            renderer.close()
        self.renderers = []
