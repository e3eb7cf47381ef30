"""4-DOF pose graph (x, y, z, yaw) of keyframes, solved with gtsam.

Why 4-DOF: VIO observes roll and pitch from gravity, so its drift is a yaw rotation plus a translation
(VINS-Mono's ``optimize4DoF``, which writes a 4-DOF residual in Ceres with yaw as the only rotation
parameter). Here each node is a gtsam ``Pose3`` holding only the keyframe's *yaw frame* ``(Rz(yaw), p_WB)``
and each edge is a ``BetweenFactorPose3`` whose measurement is the 4-DOF relative pose ``(Rz(dyaw), dp)`` of
:func:`viotb.vio.loop.frames.relative_4dof`, with sigmas ``(tilt, tilt, yaw, t, t, t)`` in gtsam's tangent
order (rotation first). The tilt sigma is tiny, so roll and pitch of every node stay at zero (the anchors
fix them) and the solve is the 4-DOF problem; since ``|Rz(yaw_i)^T dp| = |R_WBi^T dp|``, the isotropic
translation cost equals VINS-Mono's residual in i's full body frame. Roll and pitch of a keyframe are
re-attached from the odometry afterwards. Loop edges carry a robust kernel (Huber by default; a
redescending Cauchy kernel, tested, lets a long drift, many sigmas off at the initial values, switch the
true loops off); odometry edges do not.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np
from viotb.vio.lie import rotz, yaw_from_rotmat
from viotb.vio.loop.params import PoseGraphParams


@dataclass(frozen=True)
class Edge4Dof:
    """A 4-DOF relative-pose measurement of node j in the yaw frame of node i.

    Attributes:
        i: Key of the first node.
        j: Key of the second node.
        dyaw_rad: ``yaw_j - yaw_i`` (rad).
        dp_m: ``Rz(yaw_i)^T (p_j - p_i)`` (m), shape (3,).
        is_loop: Loop edge (robust kernel, loop sigmas) or odometry edge.
        to_map: A loop edge to a keyframe of a loaded (fixed) map, with the map-loop sigmas.
    """

    i: int
    j: int
    dyaw_rad: float
    dp_m: np.ndarray
    is_loop: bool = False
    to_map: bool = False


@dataclass(frozen=True)
class SolveReport:
    """What one solve did.

    Attributes:
        nodes: Nodes in the problem.
        edges: Edges in the problem.
        error_before: gtsam's total (robust) error at the initial values.
        error_after: gtsam's total error at the solution.
        iterations: Levenberg-Marquardt iterations.
        solve_ms: Wall time of building and solving (ms).
    """

    nodes: int
    edges: int
    error_before: float
    error_after: float
    iterations: int
    solve_ms: float


class PoseGraph4Dof:
    """Nodes ``(yaw_rad, p_W)``, 4-DOF edges, fixed anchor nodes; factors are kept, values rebuilt per solve.

    Args:
        params: Sigmas, kernel and iteration bound.
    """

    def __init__(self, params: PoseGraphParams | None = None) -> None:
        """Empty graph."""
        self.params = params or PoseGraphParams()
        self._yaw_rad: dict[int, float] = {}
        self._p_W: dict[int, np.ndarray] = {}
        self._fixed: set[int] = set()
        self.edges: list[Edge4Dof] = []
        self._graph = gtsam.NonlinearFactorGraph()  # grown with each node and edge, not rebuilt per solve
        self._noise_models = {False: self._noise(False), True: self._noise(True)}
        self._map_noise = self._noise(True, to_map=True)
        self._anchor = gtsam.noiseModel.Isotropic.Sigma(6, self.params.anchor_sigma)

    def __contains__(self, key: int) -> bool:
        """True when ``key`` is a node."""
        return key in self._yaw_rad

    def __len__(self) -> int:
        """Number of nodes."""
        return len(self._yaw_rad)

    def add_node(self, key: int, yaw_rad: float, p_W: np.ndarray, fixed: bool = False) -> None:
        """Add (or reset) a node with its initial value; ``fixed`` nodes are held by a tight prior."""
        self._yaw_rad[key] = float(yaw_rad)
        self._p_W[key] = np.asarray(p_W, dtype=float).copy()
        if fixed and key not in self._fixed:
            self._fixed.add(key)
            pose = gtsam.Pose3(gtsam.Rot3(rotz(yaw_rad)), self._p_W[key])
            self._graph.add(gtsam.PriorFactorPose3(key, pose, self._anchor))

    def add_edge(self, edge: Edge4Dof) -> None:
        """Add a measurement between two existing nodes.

        Raises:
            KeyError: A node of the edge is missing.
        """
        for key in (edge.i, edge.j):
            if key not in self._yaw_rad:
                raise KeyError(f"pose graph has no node {key}")
        self.edges.append(edge)
        measured = gtsam.Pose3(gtsam.Rot3(rotz(edge.dyaw_rad)), np.asarray(edge.dp_m, dtype=float))
        self._graph.add(gtsam.BetweenFactorPose3(edge.i, edge.j, measured, self._edge_noise(edge)))

    def node(self, key: int) -> tuple[float, np.ndarray]:
        """Current ``(yaw_rad, p_W)`` of a node."""
        return self._yaw_rad[key], self._p_W[key].copy()

    def _edge_noise(self, edge: Edge4Dof):
        """The edge's noise model: the shared one, or an odometry edge's that grows with its length."""
        pg = self.params
        per_m = (pg.odometry_sigma_translation_per_m, pg.odometry_sigma_yaw_rad_per_m)
        if edge.is_loop and edge.to_map:
            return self._map_noise
        if edge.is_loop or per_m == (0.0, 0.0):
            return self._noise_models[edge.is_loop]
        length_m = float(np.linalg.norm(edge.dp_m))
        s_t = pg.odometry_sigma_translation_m + per_m[0] * length_m
        s_yaw = pg.odometry_sigma_yaw_rad + per_m[1] * length_m
        return gtsam.noiseModel.Diagonal.Sigmas(
            np.array([pg.tilt_sigma_rad, pg.tilt_sigma_rad, s_yaw, s_t, s_t, s_t])
        )

    def _noise(self, is_loop: bool, to_map: bool = False):
        pg = self.params
        if to_map:
            s_t, s_yaw = pg.map_loop_sigma_translation_m, pg.map_loop_sigma_yaw_rad
        elif is_loop:
            s_t, s_yaw = pg.loop_sigma_translation_m, pg.loop_sigma_yaw_rad
        else:
            s_t, s_yaw = pg.odometry_sigma_translation_m, pg.odometry_sigma_yaw_rad
        base = gtsam.noiseModel.Diagonal.Sigmas(
            np.array([pg.tilt_sigma_rad, pg.tilt_sigma_rad, s_yaw, s_t, s_t, s_t])
        )
        if not is_loop or pg.robust_kernel == "none":
            return base
        if pg.robust_kernel == "cauchy":
            kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(pg.robust_k)
        elif pg.robust_kernel == "huber":
            kernel = gtsam.noiseModel.mEstimator.Huber.Create(pg.robust_k)
        else:
            raise ValueError(f"robust_kernel must be 'cauchy', 'huber' or 'none', got {pg.robust_kernel!r}")
        return gtsam.noiseModel.Robust.Create(kernel, base)

    def optimize(self) -> SolveReport:
        """Solve with Levenberg-Marquardt from the current values and store the result in the nodes.

        Raises:
            ValueError: No fixed node (the gauge would be free).
        """
        if not self._fixed:
            raise ValueError("pose graph needs at least one fixed node")
        t0 = time.perf_counter()
        graph = self._graph
        values = gtsam.Values()
        for key, yaw in self._yaw_rad.items():
            values.insert(key, gtsam.Pose3(gtsam.Rot3(rotz(yaw)), self._p_W[key]))
        lm_params = gtsam.LevenbergMarquardtParams()
        lm_params.setMaxIterations(self.params.max_iterations)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, lm_params)
        error_before = graph.error(values)
        result = optimizer.optimize()
        for key in self._yaw_rad:
            pose = result.atPose3(key)
            self._yaw_rad[key] = yaw_from_rotmat(pose.rotation().matrix())
            self._p_W[key] = np.asarray(pose.translation(), dtype=float).copy()
        return SolveReport(
            nodes=len(self._yaw_rad),
            edges=len(self.edges),
            error_before=float(error_before),
            error_after=float(graph.error(result)),
            iterations=int(optimizer.iterations()),
            solve_ms=(time.perf_counter() - t0) * 1e3,
        )
