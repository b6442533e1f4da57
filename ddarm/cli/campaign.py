"""`ddarm campaign FILE.yaml`: many tunings, their searches on the process pool or a Ray cluster, each job's gains
then checked through the ROS graph, one run folder and one summary for all."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from tqdm import tqdm

from ddarm.cli.output import print_json
from ddarm.cli.reproduce import job_count
from ddarm.recording.bags import BagError, checked_output_location
from ddarm.reporting.progress import Progress


def add_campaign_parser(commands) -> None:
    campaign = commands.add_parser('campaign', help='run a list of tunings (arms × motions × controllers × scenarios) '
                                                   'into one run folder and one summary')
    campaign.add_argument('file', metavar='FILE.yaml', help='the campaign file (docs/tuning.md: `ddarm campaign`)')
    campaign.add_argument('--out', metavar='DIR',
                          help='the run folder, new (default: runs/campaign-<file name>-<time>)')
    where = campaign.add_mutually_exclusive_group()
    where.add_argument('--jobs', type=job_count, metavar='N',
                       help='searches run at once on this machine, each a process with its share of the cores; the '
                            'results do not depend on it (default: the cores this process may use)')
    where.add_argument('--ray', metavar='ADDRESS',
                       help='run the searches as tasks on the Ray cluster at ADDRESS (host:port); Ray has no '
                            'authentication: use a cluster on 127.0.0.1 or a trusted network only')
    campaign.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap', help='bag storage (mcap)')
    campaign.add_argument('--json', action='store_true', help='print the summary (summary.json) on stdout')
    campaign.set_defaults(handler=command_campaign, starts_ros=True)


def command_campaign(args: argparse.Namespace) -> int:
    from ddarm.tuning.campaign import load_campaign, search_jobs
    from ddarm.tuning.outputs import check_outputs

    campaign = load_campaign(args.file)  # every job checked: nothing is searched before the file is right
    out = None
    if args.out is not None:  # the run folder is new, the folder it goes in is not
        try:
            out = checked_output_location(args.out)
        except BagError as error:
            raise BagError(f'--out {error}') from error
    runs, name = (str(out.parent), out.name) if out else ('runs', None)
    check_outputs(None, runs, name)
    for warning in campaign.warnings:
        print(f'ddarm campaign: WARNING: {warning}', file=sys.stderr)
    jobs = search_jobs(campaign)
    if args.ray:
        from ddarm.tuning.cluster import RayCluster

        with RayCluster(args.ray) as cluster:  # connected and its nodes checked before the run folder exists
            # A Ray task reports only its end, not its progress.
            summary, path = _campaign_run(args, campaign, runs, name, jobs, lambda jobs, on_progress, on_done:
                                          cluster.run_jobs(jobs, on_done=on_done))
    else:
        from ddarm.tuning.jobs import default_workers, run_jobs

        workers = args.jobs or default_workers()
        summary, path = _campaign_run(args, campaign, runs, name, jobs,
                                      lambda jobs, on_progress, on_done: run_jobs(
                                          jobs, workers, on_progress=on_progress, on_done=on_done))
    if args.json:
        print_json(summary)
    else:
        print_campaign(summary, path)
    return 0 if not summary['failed'] else 1


def _campaign_run(args: argparse.Namespace, campaign, runs: str, name: str | None, jobs: list, run_searches
                  ) -> tuple[dict, Path]:
    """The run folder made, the searches run by `run_searches(jobs, on_progress, on_done)` (the pool's or the
    cluster's), each job's gains checked through the ROS graph, the summary written; a stop marks the run
    interrupted."""
    from ddarm.ros.session import GraphSession
    from ddarm.tuning.campaign import FILE_COPY_NAME, JobRecords, check_jobs, search_record, write_summary
    from ddarm.tuning.outputs import run_folder

    done: dict = {}
    by_name = {job.name: job for job in campaign.jobs}
    with run_folder('campaign', Path(args.file).stem, runs, name, shlex.join(['ddarm', *args.argv])) as run:
        run.write_text(FILE_COPY_NAME, campaign.text)
        records = JobRecords(run, campaign)
        with Progress(sum(job.total for job in jobs), f'{len(jobs)} searches', quiet=args.json) as bar:
            def progress(job, episodes, best) -> None:
                done[job.key] = episodes
                bar.update(sum(done.values()))

            def finished(job, found) -> None:
                records.add(search_record(by_name[job.key], found))  # a search done is kept, whatever comes next
                progress(job, job.total, None)
                if not args.json:
                    search = found.tuning.search if found.tuning else None
                    tqdm.write(f'  {job.label}: ' + (
                        f'{job.index_name} = {search.index:.6g} after {search.episodes} episodes'
                        + ('' if search.converged else f', {search.certainty(hint=False)}')
                        if search else f'FAILED: {found.error}'), file=sys.stderr)

            found = run_searches(jobs, progress, finished)

        def checked(record: dict) -> None:
            if not args.json:
                print(f"  {record['name']}: " + (f"{record['index']} = {record['bag_index']:.6g} from {record['bag']}"
                                               if record['status'] == 'ok' else f"FAILED: {record['reason']}"),
                      file=sys.stderr, flush=True)

        if not args.json:
            print("checking each job's gains through the ROS graph (lockstep), recorded …", file=sys.stderr, flush=True)
        # One session for every job: its nodes restart only for another law or arm.
        with GraphSession(run.path / 'nodes') as session:
            checked_records = check_jobs(session, run, campaign, found, args.storage, on_record=checked,
                                         records=records)
        return write_summary(run, campaign, checked_records), run.path


def print_campaign(summary: dict, path: Path) -> None:
    jobs = summary['jobs']
    width = max(len(record['name']) for record in jobs)
    for record in jobs:
        if record['status'] == 'ok':
            print(f"{record['name']:<{width}}  {record['index']:<2} search {record['search_index']:.6g}  "
                  f"bag {record['bag_index']:.6g}  ok"
                  + ('' if record['converged'] else f"; WARNING: {record['certainty']}"))
        else:
            print(f"{record['name']:<{width}}  FAILED: {record['reason']}")
    failed = summary['failed']
    print(f"{len(jobs) - len(failed)} of {len(jobs)} jobs ok" + (f"; failed: {', '.join(failed)}" if failed else '')
          + f'; summary {path / "SUMMARY.md"}, {path / "summary.json"}')
