"""Every MJCF name and file that code refers to, in one place (cf. mujoco_playground go1_constants)."""

from __future__ import annotations

from pathlib import Path

MODELS_DIR = Path(__file__).resolve().parent
"""Folder holding the MJCF files (installed as package data)."""

# Files.
QUADROTOR_XML = "quadrotor.xml"
HEADSET_XML = "headset.xml"
SCENE_XMLS = {
    "empty": "scene_empty.xml",
    "textured_room": "scene_textured_room.xml",
    "blank_wall": "scene_blank_wall.xml",
    "dark_room": "scene_dark_room.xml",
    "pillars": "scene_pillars.xml",
}
"""Scene name -> MJCF file with world geometry only (no vehicle)."""

VEHICLE_XMLS = {"quadrotor": QUADROTOR_XML, "headset": HEADSET_XML}
"""Vehicle name -> MJCF file."""

COMMON_XMLS = ("common/visual.xml", "common/materials.xml", "common/skybox.xml", "common/room.xml")
"""Shared pieces included by the scene files (not loadable alone)."""

SCENE_BOUNDS_M = {
    "empty": ((-20.0, -20.0, 0.0), (20.0, 20.0, 20.0)),
    "textured_room": ((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0)),
    "blank_wall": ((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0)),
    "dark_room": ((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0)),
    "pillars": ((-15.0, -15.0, 0.0), (15.0, 15.0, 20.0)),
}
"""Scene name -> ((x, y, z) min, (x, y, z) max) (m): the free space a vehicle may occupy (room interior)."""

# Scene geometry referred to by code and tests.
FLOOR_GEOM = "floor"
GROUND_GEOM = "ground"
ROOM_WALL_GEOMS = ("wall_north", "wall_south", "wall_east", "wall_west")

# Quadrotor.
QUAD_BODY = "quadrotor"
QUAD_FREEJOINT = "quadrotor_root"
QUAD_MOTORS = ("motor0", "motor1", "motor2", "motor3")
QUAD_ROTOR_SITES = ("rotor0", "rotor1", "rotor2", "rotor3")
HOVER_KEYFRAME = "hover"
CHASE_CAMERA = "chase"
"""Third-person camera (quadrotor: trackcom, behind and above) for Gymnasium's rgb_array view."""
QUAD_MASS_KG = 1.2
"""Quadrotor mass (kg), as in quadrotor.xml (tests check the two agree)."""

# Headset rig (kinematically driven head).
HEAD_BODY = "head"
HOME_KEYFRAME = "home"
"""Headset keyframe: standing at the origin, eyes 1.6 m above the floor, looking along +x_W."""
HEADSET_CAMERAS = ("head_cam0", "head_cam1")
"""Headset stereo tracking cameras (left, right), global shutter, looking along +x_B (``onboard`` stays the
single centre camera)."""
HEADSET_STEREO_BASELINE_M = 0.10
"""Distance between the two headset tracking cameras (m), along y_B."""
HEADSET_CAMERA_FOVY_DEG = 100.0
"""Vertical field of view of the (pinhole-rendered) headset tracking cameras (deg)."""

VEHICLE_BODIES = {"quadrotor": QUAD_BODY, "headset": HEAD_BODY}
"""Vehicle name -> its root body."""
DEFAULT_KEYFRAMES = {"quadrotor": HOVER_KEYFRAME, "headset": HOME_KEYFRAME}
"""Vehicle name -> its starting keyframe."""

# Shared by both vehicles.
IMU_SITE = "imu"
CAMERA_SITE = "camera"
ONBOARD_CAMERA = "onboard"
GYRO_SENSOR = "gyro"
ACCEL_SENSOR = "accelerometer"
IMU_POS_SENSOR = "imu_pos"
IMU_QUAT_SENSOR = "imu_quat"
