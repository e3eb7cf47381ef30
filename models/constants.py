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
}
"""Scene name -> MJCF file with world geometry only (no vehicle)."""

VEHICLE_XMLS = {"quadrotor": QUADROTOR_XML, "headset": HEADSET_XML}
"""Vehicle name -> MJCF file."""

# Quadrotor.
QUAD_BODY = "quadrotor"
QUAD_FREEJOINT = "quadrotor_root"
QUAD_MOTORS = ("motor0", "motor1", "motor2", "motor3")
QUAD_ROTOR_SITES = ("rotor0", "rotor1", "rotor2", "rotor3")
HOVER_KEYFRAME = "hover"

# Headset rig (kinematically driven head).
HEAD_BODY = "head"

# Shared by both vehicles.
IMU_SITE = "imu"
CAMERA_SITE = "camera"
ONBOARD_CAMERA = "onboard"
GYRO_SENSOR = "gyro"
ACCEL_SENSOR = "accelerometer"
IMU_POS_SENSOR = "imu_pos"
IMU_QUAT_SENSOR = "imu_quat"
