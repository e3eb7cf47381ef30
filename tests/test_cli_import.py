"""``viotb --help`` stays light: importing the CLI loads none of the simulation or evaluation stack.

A proxy for the import-time budget (0.5 s) that does not depend on the machine's load: the heavy modules
(MuJoCo, SciPy, the estimators, the sweep engine) load only inside the commands that need them.
"""

import subprocess
import sys
from pathlib import Path

import pytest

HEAVY = (
    "mujoco",
    "scipy",
    "numba",
    "cv2",
    "matplotlib",
    "viotb.vio.msckf",
    "viotb.envs.data.evaluate",
    "viotb.envs.tools.sweep.engine",
    "viotb.envs.run.fly",
)


def test_cli_import_loads_no_heavy_module():
    code = f"import sys, viotb.envs.tools.cli\nprint(','.join(m for m in {HEAVY!r} if m in sys.modules))\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"imported by `viotb --help`: {out.stdout.strip()}"


def test_sweep_package_names_resolve_lazily():
    import importlib.util

    from viotb.envs.tools import sweep

    assert set(sweep.__all__) == set(sweep._HOMES)
    for name, home in sweep._HOMES.items():  # each name is defined in the module it is loaded from
        text = Path(importlib.util.find_spec(f"viotb.envs.tools.sweep.{home}").origin).read_text()
        assert f"def {name}(" in text or f"class {name}" in text, (name, home)
    with pytest.raises(AttributeError, match="no_such_name"):
        _ = sweep.no_such_name
