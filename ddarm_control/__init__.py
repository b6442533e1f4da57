"""The sampled-data control laws of the paper and the rules that choose their gains (no ROS)."""
