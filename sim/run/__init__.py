"""One run: the SimPy run loop, each robot's on-board SLAM lane jobs, the scheduler
lanes, the rerun recording, and running a scenario into its results folder."""
