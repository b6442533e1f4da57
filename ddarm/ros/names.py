"""Names on the graph: fully qualified node names, and the remapping rules that put a node in a namespace."""

from __future__ import annotations

from ddarm.ros.interface import CLOCK_TOPIC, DIAGNOSTICS_TOPIC


def fully_qualified(name: str, namespace: str) -> str:
    return f"{namespace.rstrip('/')}/{name}"


def namespace_arguments(namespace: str) -> list[str]:
    """--ros-args rules that put a node, its relative topics and the absolute /clock and /diagnostics in `namespace`."""
    if not namespace or namespace == '/':
        return []
    return ['-r', f'__ns:={namespace}', '-r', f'{CLOCK_TOPIC}:={namespace}{CLOCK_TOPIC}',
            '-r', f'{DIAGNOSTICS_TOPIC}:={namespace}{DIAGNOSTICS_TOPIC}']

