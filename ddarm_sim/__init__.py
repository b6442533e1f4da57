"""The simulated direct-drive arm: its model, programmed motions and plant (no ROS)."""
