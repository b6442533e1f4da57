"""`ddarm reproduce`: the paper's Tables 2-4 and section 2 through the ROS graph, with a report."""

from __future__ import annotations

import argparse
import contextlib
import shlex
import sys
import time

from tqdm import tqdm

from ddarm.cli.arguments import whole_number
from ddarm.interrupts import critical_section
from ddarm.reporting.progress import Progress
from ddarm.strict_json import json_text


MAX_JOBS = 64
# An argparse type: how many searches run at once.
job_count = whole_number(1, MAX_JOBS)


def command_reproduce(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    from ddarm.recording.bags import checked_output_path
    from ddarm.paper.experiments import Budget, Reproduction
    from ddarm.recording.runs import RunFolder
    from ddarm.tuning.jobs import default_workers

    out = checked_output_path(args.out)
    command = shlex.join(['ddarm', *args.argv])

    def progress(message: str) -> None:
        # Through tqdm, which clears the searches' bars on a terminal, writes the line and draws them again.
        tqdm.write(f'[{time.perf_counter() - started:6.1f} s] {message}', file=sys.stderr)

    # The folder's summary.json says `running` until the report is written: an interrupted or
    # killed reproduction is never taken for a finished one.
    with RunFolder(out.name, out.parent, command=command) as run:
        reproduction = Reproduction(out, Budget.quick() if args.quick else Budget.full(), command, progress,
                                    lambda label, total, index_name, position: Progress(
                                        total, label, index_name=index_name, position=position))
        # The searches first: their workers come up while this process starts the ROS graph. Each reported
        # episode runs as soon as the searches it needs are done, while the others go on.
        jobs = args.jobs or default_workers()
        with reproduction.start_searches(jobs) as searches:
            from ddarm.ros.session import GraphSession
            from ddarm.ros.session_process import SessionProcess

            with contextlib.ExitStack() as sessions:
                # As many graph sessions as searches, each in a namespace of its own with its own nodes; several
                # each in a process of its own, so that their drivers' work runs on every core.
                count = min(jobs, reproduction.episode_groups)
                session_kind = GraphSession if count == 1 else SessionProcess
                recorders = [sessions.enter_context(session_kind(out / 'nodes' / f'session-{number}'))
                             for number in range(count)]
                for session in recorders:
                    session.prepare(reproduction.first_episode())
                progress(f'every reported episode runs through the ROS graph (lockstep, {count} session'
                         f"{'s' if count > 1 else ''}), recorded, as its gains are found")
                reproduction.run_episodes(recorders, searches)
        reproduction.judge_claims()
        results = reproduction.results
        results.wall_time_s = time.perf_counter() - started
        # Every episode is done: a stop now waits for the report (plotting code turns a stop into errors of its own).
        with critical_section():
            from ddarm.paper.report import write_report
            from ddarm.paper.schema import Results

            (out / 'results.json').write_text(json_text(results.to_json(), indent=2))
            # The report reads the file back through the schema: what it shows is what results.json holds.
            written = write_report(out, Results.load(out / 'results.json'))
            run.finish('complete', report=str(out / 'REPORT.md'))
    progress(f'done: {out / "REPORT.md"} ({len(written)} files), results in {out / "results.json"}')
    for claim in results.claims:
        print(f"{'REPRODUCED    ' if claim.reproduced else 'NOT REPRODUCED'}  {claim.claim}: {claim.evidence}")
    return 0
