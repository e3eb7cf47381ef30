"""Flight outputs a person looks at: PNG plots (matplotlib, Agg) and a rerun ``.rrd`` recording."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from viotb.envs.run.closed_loop import ClosedLoopSim
from viotb.envs.run.fly import FlightLog


def save_plots(log: FlightLog, out_dir: Path) -> list[Path]:
    """Write the flight's PNG plots into ``out_dir`` and return their paths.

    Plots: top view of truth vs estimate vs setpoint; position error per axis with the filter's 3-sigma
    bounds; tracked features per frame; motor commands.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t = np.asarray(log.t_s)
    p_true, p_est = np.asarray(log.p_true_W), np.asarray(log.p_est_W)
    p_set, sig = np.asarray(log.p_set_W), np.asarray(log.p_sigma_W)
    paths = []

    fig, ax = plt.subplots(figsize=(6, 6))
    ax.plot(p_true[:, 0], p_true[:, 1], "k-", lw=1.5, label="truth")
    ax.plot(p_est[:, 0], p_est[:, 1], "C1--", lw=1.2, label="estimate (VIO)")
    ax.plot(p_set[:, 0], p_set[:, 1], "C2:", lw=1.0, label="setpoint")
    ax.set_xlabel("x_W [m]")
    ax.set_ylabel("y_W [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend()
    ax.set_title("Top view")
    paths.append(_save(fig, out_dir / "top_view.png"))

    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    err = p_est - p_true
    for k, name in enumerate("xyz"):
        axes[k].plot(t, err[:, k], "C0", lw=1.0, label="estimate - truth")
        axes[k].fill_between(t, -3 * sig[:, k], 3 * sig[:, k], color="C0", alpha=0.15, label="3 sigma")
        axes[k].set_ylabel(f"{name} error [m]")
    axes[0].legend(loc="upper left")
    axes[-1].set_xlabel("t [s]")
    fig.suptitle("Position error of the estimate with filter 3-sigma bounds")
    paths.append(_save(fig, out_dir / "position_error.png"))

    fig, ax = plt.subplots(figsize=(8, 3))
    ax.plot(log.frame_t_s, log.frame_features, "C3.-", lw=0.8, ms=2)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("tracked features")
    ax.set_title("Features per frame")
    paths.append(_save(fig, out_dir / "features.png"))

    fig, ax = plt.subplots(figsize=(8, 3))
    thr = np.asarray(log.thrusts_N)
    for k in range(thr.shape[1]):
        ax.plot(t, thr[:, k], lw=0.8, label=f"motor {k}")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("thrust [N]")
    ax.legend(ncol=4)
    ax.set_title("Motor commands")
    paths.append(_save(fig, out_dir / "motors.png"))
    return paths


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


class RerunRecorder:
    """Streams a flight into a rerun ``.rrd`` file (no viewer, no global recording).

    Entities: ``world/truth`` and ``world/estimate`` (trajectories), ``world/estimate/cov`` (3-sigma position
    ellipsoid), ``camera/image`` with ``camera/image/features``, ``imu/gyro/*``, ``imu/accel/*`` and
    ``motors/*`` scalars.

    Args:
        path: Output ``.rrd`` file.
        image_every: Log every n-th delivered camera frame.
    """

    def __init__(self, path: Path, image_every: int = 1) -> None:
        """Open the recording stream and save it to ``path``."""
        import rerun as rr

        self._rr = rr
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._rec = rr.RecordingStream(application_id="viotb", recording_id="viotb-demo")
        self._rec.save(str(self.path))
        self._image_every = max(1, image_every)
        self._frames = 0
        self._last_frame_id = None
        self._ticks = 0

    def __call__(self, loop: ClosedLoopSim, log: FlightLog) -> None:
        """The ``on_tick`` hook of :func:`viotb.envs.run.fly.fly`."""
        rr, rec = self._rr, self._rec
        self._ticks += 1
        rec.set_time("sim_time", duration=float(loop.t_s))
        if self._ticks % 5 == 0:
            for k, name in enumerate("xyz"):
                rec.log(f"imu/gyro/{name}", rr.Scalars(float(log.gyro_B[-1][k])))
                rec.log(f"imu/accel/{name}", rr.Scalars(float(log.accel_B[-1][k])))
            for k, thrust in enumerate(log.thrusts_N[-1]):
                rec.log(f"motors/{k}", rr.Scalars(float(thrust)))
        if self._ticks % 25 == 0:
            rec.log("world/truth", rr.LineStrips3D([np.asarray(log.p_true_W)], colors=[[40, 40, 40]]))
            p_est = np.asarray(log.p_est_W)
            p_est = p_est[np.all(np.isfinite(p_est), axis=1)]
            if len(p_est):
                rec.log("world/estimate", rr.LineStrips3D([p_est], colors=[[230, 120, 20]]))
                sig = np.asarray(log.p_sigma_W[-1])
                if np.all(np.isfinite(sig)):
                    rec.log(
                        "world/estimate/cov",
                        rr.Ellipsoids3D(
                            centers=[p_est[-1]], half_sizes=[3.0 * sig + 1e-4], colors=[[230, 120, 20]]
                        ),
                    )
        frame = loop.last_frame
        if frame is not None and id(frame) != self._last_frame_id:
            self._last_frame_id = id(frame)
            self._frames += 1
            if self._frames % self._image_every == 0 and frame.image is not None:
                rec.log("camera/image", rr.Image(frame.image))
                uv = loop.estimator.last_tracks_px()
                if len(uv):
                    rec.log("camera/image/features", rr.Points2D(uv, radii=1.5, colors=[[0, 255, 0]]))

    def close(self) -> None:
        """Flush and close the file."""
        self._rec.flush()
        self._rec.disconnect()
