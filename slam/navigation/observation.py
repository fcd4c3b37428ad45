"""Active mutual observation: which peer to point the cameras at (beyond the thesis).

The thesis's robots detect each other's AprilTag markers only when a peer happens to be in
view (6.2, 9.3); its future work proposes to look for them on purpose. A robot that
believes a peer is within ``observe_range_m`` and has not detected it for
``observe_interval_s`` points its head at the peer's believed position (the rover's pan,
sim/robots/lru.py), so that a detection ``d`` (thesis 4.2.2) ties the two graphs. Where a
peer is believed to be: on the robot's graph once it connects them (eq. 4.6), before that
on the peer's own periodic estimate in its odometry frame and its deployment pose (both
robots know the mission plan, as they share goals in the mission frame).

Pure: believed positions and detection times in, the peer to look at out.
"""

from __future__ import annotations

import numpy as np


def peer_to_observe(
    robot_xy, peers: dict[str, np.ndarray], last_detected: dict[str, float], now: float, range_m: float, interval_s: float
) -> tuple[str, np.ndarray] | None:
    """The nearest peer within ``range_m`` of ``robot_xy`` not detected for ``interval_s``
    (``peers``: believed positions, mission frame; ``last_detected``: time of this robot's
    latest detection of each), with its position; None if there is none."""
    robot = np.asarray(robot_xy, float)[:2]
    best = None
    for name in sorted(peers):
        xy = np.asarray(peers[name], float)[:2]
        d = float(np.linalg.norm(xy - robot))
        if d > range_m or now - last_detected.get(name, -np.inf) < interval_s:
            continue
        if best is None or d < best[0]:
            best = (d, name, xy)
    return None if best is None else (best[1], best[2])
