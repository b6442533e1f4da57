"""Runs on disk: rosbag2 bags (bags), run folders (runs), gains files (gains_file)."""

from pathlib import Path

# The folder that holds the run folders, unless a command or the tuner node names another. Here, not in runs: the
# nodes' parameter schema names it, and importing runs (with rosbags' type stores) added 0.2 s to each node's start.
DEFAULT_ROOT = Path('runs')
