"""The DDS transport of the node processes ddarm starts: shared memory, unless the user configured Fast DDS."""

from __future__ import annotations

import os

# What configures Fast DDS's transports: set by the user, it is theirs to keep.
FAST_DDS_SETTINGS = ('FASTDDS_BUILTIN_TRANSPORTS', 'FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')


def node_environment(environment: dict | None = None) -> dict:
    """`environment` (default: this process's) with Fast DDS on shared memory alone, unless it configures Fast DDS.

    With its default transports a session's samples went over UDP loopback here: measured side by side
    (`ddarm bench --ros`), lockstep ran at about 1.7 times the rate on shared memory alone, and the bare
    round trip at 1.4 times. Nodes on shared memory alone are reachable from this machine only, which is
    what a session's private graph is; a participant with the default transports (this process's driver,
    `ros2 topic echo`) still hears them, over shared memory.
    """
    environment = dict(os.environ if environment is None else environment)
    if not any(name in environment for name in FAST_DDS_SETTINGS):
        environment['FASTDDS_BUILTIN_TRANSPORTS'] = 'SHM'
    return environment
