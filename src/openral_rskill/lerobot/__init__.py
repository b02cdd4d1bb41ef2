"""LeRobot checkpoints as openral skills: the folder read without torch, observations mapped, LeRobot's own loading."""
