"""The real-time parameters every ddarm node process has (realtime_priority, cpu_affinity): declared alike on the
plant and the controllers (ddarm.ros.parameter_schema.SCHEDULING), applied to the whole process when set, and refused, naming what the OS needs, when
it will not (ddarm.realtime); the old scheduling then stays."""

from __future__ import annotations

from ddarm.realtime import ProcessScheduling, Scheduling, SchedulingError

SCHEDULING_PARAMETERS = ('realtime_priority', 'cpu_affinity')


def requested(values: dict) -> tuple[int, tuple[int, ...]]:
    cores = values['cpu_affinity']
    return int(values['realtime_priority']), tuple(int(core) for core in (cores if cores is not None else ()))


class NodeScheduling:
    """A node process's scheduling as its parameters ask: applied at start (a refusal refuses the node) and at
    each change (a refusal refuses the change)."""

    def __init__(self, values: dict) -> None:
        self.process = ProcessScheduling()
        self.asked = (0, ())
        self.update(values)

    def update(self, values: dict) -> None:
        """Apply what `values` asks for, if it differs from what was asked before; SchedulingError if refused."""
        asked = requested(values)
        if asked != self.asked:
            self.process.apply(*asked)
            self.asked = asked

    def refusal(self, values: dict) -> str | None:
        """For an on-set callback: None once `values`' scheduling is applied, else why the OS refused it."""
        try:
            self.update(values)
        except SchedulingError as error:
            return str(error)
        return None

    def current(self) -> Scheduling:
        """The calling thread's scheduling, as the kernel reports it."""
        return self.process.current()
