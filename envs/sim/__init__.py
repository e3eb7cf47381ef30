"""sim wing: the simulated world and its sensors (MuJoCo, renderer, IMU, camera timing, landmarks, faults)."""
