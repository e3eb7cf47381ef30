"""sim wing: the simulated world and its sensors (MuJoCo wrapper, renderer, IMU and camera timing, landmarks, faults)."""
