"""The simulated world: procedural terrain, markers, the stereo rig, sensor models and the
composed MJCF (robots themselves live in :mod:`sim.robots`)."""
