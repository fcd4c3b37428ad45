"""Imported by the local pool's fork server (sim/batch/execute.py): the simulator's modules and the
compiled voxel kernels (slam/voxels.py), loaded once in the server, so that every run forked from it
starts with them instead of loading them again (about 1 s per run)."""

import sim.run.run_folder  # noqa: F401  (the simulator, imported for the forks)
from slam.voxels import compile_kernels

compile_kernels()
