"""vio-testbed: a MuJoCo quadrotor and headset rig with visual-inertial odometry in the loop.

The rooms are subpackages: ``viotb.models`` (MJCF), ``viotb.vio`` (estimators, no MuJoCo),
``viotb.envs`` (simulation, sensors, datasets, runner, Gymnasium, CLI) and ``viotb.controllers``.
"""

__version__ = "0.1.0"
