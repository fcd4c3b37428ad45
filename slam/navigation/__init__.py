"""On-board navigation on the robot's own maps: path planning (thesis 9.2.2) and exploration goals (thesis 9.3)."""
