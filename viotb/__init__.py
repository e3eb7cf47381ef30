"""vio-testbed: a MuJoCo quadrotor and headset rig with visual-inertial odometry in the loop.

The rooms are subpackages: ``viotb.models`` (MJCF), ``viotb.vio`` (estimators, no MuJoCo),
``viotb.envs`` (simulation, sensors, datasets, runner, Gymnasium, CLI) and ``viotb.controllers``.
"""

import os
import sys

_USER_SET = set(os.environ) & {"OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"}

# The estimator works on small dense matrices (tens to a few hundred rows), where multi-threaded BLAS only
# adds synchronization cost: measured 3-15x slower per frame on a loaded 2-core machine. Set before numpy
# is first imported; an explicit user setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
if "numpy" in sys.modules and "OPENBLAS_NUM_THREADS" not in _USER_SET:
    # numpy came first, so its BLAS already read the environment: limit it at run time. Besides the speed,
    # this is determinism: a threaded BLAS sums in another order, and a closed-loop flight amplifies that
    # round-off (measured on a 60 s hover, same seed: 4.4 cm RMS single-threaded, 2.4 cm threaded).
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)

__version__ = "0.1.0"
