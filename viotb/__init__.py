"""vio-testbed: a MuJoCo quadrotor and headset rig with visual-inertial odometry in the loop.

The rooms are subpackages: ``viotb.models`` (MJCF), ``viotb.vio`` (estimators, no MuJoCo),
``viotb.envs`` (simulation, sensors, datasets, runner, Gymnasium, CLI) and ``viotb.controllers``.
"""

import os

# The estimator works on small dense matrices (tens to a few hundred rows), where multi-threaded BLAS only
# adds synchronization cost: measured 3-15x slower per frame on a loaded 2-core machine. Set before numpy
# is first imported; an explicit user setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

__version__ = "0.1.0"
