"""Loop closure and relocalization: keyframes, place recognition, PnP verification, 4-DOF pose graph.

Drive it from a replay or flight loop with :class:`LoopCloser` (one ``add_frame`` per camera frame, the
estimator's pose in its own odometry frame); read the corrected pose with ``corrected_pose``.
"""

from viotb.vio.loop.closer import LoopCloser
from viotb.vio.loop.consistency import ConsistencyGate
from viotb.vio.loop.correction import CorrectionBlender
from viotb.vio.loop.frames import RigidTransform
from viotb.vio.loop.keyframes import Keyframe, KeyframeDatabase
from viotb.vio.loop.params import (
    ConsistencyParams,
    KeyframeParams,
    LoopClosureParams,
    PlaceRecognitionParams,
    PoseGraphParams,
    VerificationParams,
)
from viotb.vio.loop.pose_graph import Edge4Dof, PoseGraph4Dof
from viotb.vio.loop.records import FrameTiming, LoopClosure

__all__ = [
    "ConsistencyGate",
    "ConsistencyParams",
    "CorrectionBlender",
    "Edge4Dof",
    "FrameTiming",
    "Keyframe",
    "KeyframeDatabase",
    "KeyframeParams",
    "LoopCloser",
    "LoopClosure",
    "LoopClosureParams",
    "PlaceRecognitionParams",
    "PoseGraph4Dof",
    "PoseGraphParams",
    "RigidTransform",
    "VerificationParams",
]
