"""marsyard simulation: everything that knows MuJoCo, SimPy time or ground truth."""

import os

# MuJoCo picks its GL backend at import time; there is no display on our machines.
os.environ.setdefault("MUJOCO_GL", "egl")
