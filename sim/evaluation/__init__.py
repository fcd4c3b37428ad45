"""Everything a run is scored on against the simulator's ground truth (trajectories,
online SLAM, maps, loop closures) and the results folder that holds it."""
