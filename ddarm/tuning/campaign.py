"""A campaign: many `ddarm tune` jobs (arms × motions × controllers × scenarios, and/or listed jobs) from one YAML
file, their searches run as independent jobs, each job's best gains then recorded once as a bag and scored from it.

The file is read strictly and every job is checked (its episode, its search's arguments) before any search
starts: a refusal names the file and the key or job. A job's search is `ddarm tune`'s (ddarm.tuning.tune.tune),
a pure function of the job, so its result is the same wherever it runs (in turn, on the process pool of
ddarm.tuning.jobs, or as a Ray task: ddarm.tuning.cluster). No ROS here: the caller hands over what records
and scores the episodes (the graph session).
"""

from __future__ import annotations

import dataclasses
import errno
import json
import math
import re
import sqlite3
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol
from urllib.parse import quote

import yaml
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ddarm.control.gains import SEARCH_START_OMEGAS
from ddarm.control.laws import CONTROLLERS
from ddarm.deprecation import renamed_keys
from ddarm.episodes.indices import INDICES, PAPER_EQUATIONS
from ddarm.episodes.spec import EPISODE_DEFAULTS, EpisodeSpec, arm_joints, check_episode
from ddarm.errors import DdarmError
from ddarm.datafiles import DataFileError, read_data_file, regular_file_problem
from ddarm.motion.files import DataLoader, shown
from ddarm.motion.programmed import PAPER_TRAJECTORIES
from ddarm.recording.runs import RunFolder, write_new_file
from ddarm.reporting.text import figure_text, markdown_paragraph, markdown_text
from ddarm.tuning.jobs import Job
from ddarm.tuning.methods import DEFAULT_METHOD, DEFAULT_TUNE_BUDGET, METHODS
from ddarm.tuning.outputs import AGREEMENT, relative_difference, search_doubt, write_gains
from ddarm.tuning.robust import describe_scenario, scenario_record
from ddarm.tuning.search import SearchError, check_search, omega_starts
from ddarm.tuning.tune import Tuning, tune

# The options of `ddarm tune` a campaign sets for all its jobs (at the top) or for one (in a listed job).
OPTION_KEYS = ('index', 'method', 'budget', 'seed', 'omegas', 'period', 'delay', 'torque_limit', 'substeps')
PRODUCT_KEYS = ('arms', 'motions', 'controllers', 'scenarios')
TOP_KEYS = ('description', *PRODUCT_KEYS, 'jobs', *OPTION_KEYS)
ARM_KEYS = ('name', 'urdf', 'model_urdf')
MOTION_KEYS = ('name', 'trajectory', 'file', 'duration')
SCENARIO_KEYS = ('name', 'tau', 'mass_scale', 'external_torque', 'viscous_friction', 'coulomb_friction')
JOB_KEYS = ('name', 'arm', 'motion', 'controller', 'scenario', *OPTION_KEYS)
# Deprecated keys, each with the one it is read as (the episode's name for the law).
TOP_RENAMED, JOB_RENAMED = {'laws': 'controllers'}, {'law': 'controller'}
# A name becomes part of a job's name and so of its bag's and gains file's names: one plain word each.
NAME = re.compile(r'[A-Za-z0-9][A-Za-z0-9_+-]*')
# The longest file name made from a job's name (its bag's MCAP storage file, its gains file <name>.yaml): within
# the NAME_MAX bytes of Linux's file systems. Names are ASCII, a byte a character.
JOB_FILE_SUFFIX = '.mcap'
NAME_MAX = 255
# A campaign's jobs, the product's and the listed ones: each is checked (its episode planned) before any search, and
# each runs a search of its budget; far beyond any campaign run, and refused before the first is built.
MAX_JOBS = 1000
SUMMARY_NAME, TABLE_NAME, PLOT_NAME, FILE_COPY_NAME = 'summary.json', 'SUMMARY.md', 'index-per-job.png', 'campaign.yaml'


class CampaignError(DdarmError, ValueError):
    """A campaign file that cannot be run, named by the file and its key or job."""


@dataclass(frozen=True)
class CampaignJob:
    """One tuning of a campaign: what `ddarm tune` would do with these options.

    `template` is the episode but its gains, `arm`, `motion` and `scenario` the names of its parts, and
    `scenario_record` the scenario's τ, mass scale and P^z (ddarm.tuning.robust.scenario_record).
    """

    name: str
    arm: str
    motion: str
    controller: str
    scenario: str
    template: EpisodeSpec
    index: str
    method: str
    budget: int
    seed: int
    omegas: tuple[float, ...]

    @property
    def scenario_record(self) -> dict:
        return scenario_record(self.template, len(arm_joints(self.template)[0]))


@dataclass(frozen=True)
class Campaign:
    """A campaign file read and checked: its jobs in order, and the warnings their episodes raised."""

    path: Path
    text: str
    description: str
    jobs: tuple[CampaignJob, ...]
    warnings: tuple[str, ...]


@dataclass(frozen=True)
class JobSearch:
    """A job's search done: its tuning, or why it found no gains (`error`)."""

    tuning: Tuning | None
    error: str | None = None


def search_job(job: CampaignJob, progress=None) -> JobSearch:
    """The job's search, exactly as `ddarm tune` runs it; a search that finds no gains is a result, not a stop,
    so that the campaign's other jobs go on and this one is reported as failed."""
    try:
        return JobSearch(tune(job.template, job.index, job.method, job.budget, job.omegas, job.seed,
                              progress=progress))
    except SearchError as error:
        return JobSearch(None, str(error))


def search_jobs(campaign: Campaign) -> list[Job]:
    """The campaign's searches as independent jobs (ddarm.tuning.jobs), keyed by job name."""
    return [Job(job.name, job.name, search_job, (job,), total=job.budget, index_name=job.index)
            for job in campaign.jobs]


def _finite(number: int | float) -> bool:
    try:
        return math.isfinite(number)
    except OverflowError:  # an integer beyond a float's range
        return False


class _Reader:
    """Reads one campaign file's values, each refusal naming the file and where in it (`jobs[2].arm.urdf`)."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def fail(self, where: str, message: str):
        raise CampaignError(f'{self.path}: {where}: {message}')

    def mapping(self, where: str, data, keys: tuple[str, ...]) -> dict:
        if not isinstance(data, dict):
            self.fail(where, f'must be a mapping of {", ".join(keys)}, got {shown(data)}')
        for key in data:
            if key not in keys:
                self.fail(where, f'unknown key {shown(key)} (known: {", ".join(keys)})')
        return data

    def items(self, where: str, data) -> list:
        if not isinstance(data, list) or not data:
            self.fail(where, f'must be a non-empty list, got {shown(data)}')
        return data

    def number(self, where: str, value, *, positive: bool = False, non_negative: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not _finite(value):
            self.fail(where, f'must be a finite number, got {shown(value)}')
        if positive and value <= 0 or non_negative and value < 0:
            self.fail(where, f'must be {"positive" if positive else "at least 0"}, got {shown(value)}')
        return float(value)

    def whole(self, where: str, value, minimum: int) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            self.fail(where, f'must be a whole number of at least {minimum}, got {shown(value)}')
        return value

    def numbers(self, where: str, value, *, scalar: bool = False, positive: bool = False) -> tuple[float, ...]:
        """One number per joint (the episode checks the count); `scalar` also takes one number for every joint."""
        if scalar and not isinstance(value, list):
            return (self.number(where, value, positive=positive),)
        return tuple(self.number(f'{where}[{i}]', item, positive=positive)
                     for i, item in enumerate(self.items(where, value)))

    def choice(self, where: str, value, choices: tuple) -> str:
        if not isinstance(value, str) or value not in choices:
            self.fail(where, f'must be one of {", ".join(choices)}, got {shown(value)}')
        return value

    def name(self, where: str, value) -> str:
        if not isinstance(value, str) or not NAME.fullmatch(value):
            self.fail(where, f'must be a name of letters, digits, _, + and - (starting with a letter or digit), '
                             f'got {shown(value)}')
        return value

    def file(self, where: str, value) -> str:
        if not isinstance(value, str) or not value:
            self.fail(where, f'must be a file path, got {shown(value)}')
        path = (self.path.parent / Path(value).expanduser()).resolve()  # relative paths from the campaign file
        try:
            problem = regular_file_problem(path.stat())
        except FileNotFoundError:
            self.fail(where, f'{path}: no such file')
        except OSError as error:
            self.fail(where, f'{path} cannot be read: {error.strerror}')
        if problem is not None:
            self.fail(where, f'{path} {problem}')
        return str(path)

    def options(self, where: str, data: dict) -> dict:
        """The `ddarm tune` options set in `data`, checked."""
        options = {}
        for key in OPTION_KEYS:
            if key not in data:
                continue
            value, at = data[key], f'{where}.{key}' if where else key
            if key == 'index':
                # YAML reads the paper's 2.5 and 3.2 as numbers: they name I1 and I as on the command line.
                text = str(value) if isinstance(value, float) else value
                options[key] = PAPER_EQUATIONS.get(text, text) if isinstance(text, str) else text
                self.choice(at, options[key], INDICES + tuple(PAPER_EQUATIONS))
            elif key == 'method':
                options[key] = self.choice(at, value, METHODS)
            elif key == 'budget':
                options[key] = self.whole(at, value, 1)
            elif key in ('seed', 'delay'):
                options[key] = self.whole(at, value, 0)
            elif key == 'substeps':
                options[key] = self.whole(at, value, 1)
            elif key == 'omegas':
                options[key] = self.numbers(at, value, positive=True)
            elif key == 'period':
                options[key] = self.number(at, value, positive=True)
            elif isinstance(value, str):  # torque_limit
                options[key] = self.choice(at, value, ('none', 'paper', 'urdf'))
            else:
                options[key] = self.numbers(at, value, positive=True)
        return options

    def arm(self, where: str, data) -> dict:
        data = self.mapping(where, data, ARM_KEYS)
        arm = {key: self.file(f'{where}.{key}', data[key]) for key in ('urdf', 'model_urdf') if key in data}
        if 'model_urdf' in arm and 'urdf' not in arm:
            self.fail(where, 'model_urdf is the model of a plant URDF: give urdf too')
        default = Path(arm['urdf']).stem if 'urdf' in arm else 'paper'
        return {'name': self.name(f'{where}.name', data.get('name', default)), **arm}

    def motion(self, where: str, data) -> dict:
        data = self.mapping(where, data, MOTION_KEYS)
        if ('trajectory' in data) == ('file' in data):
            self.fail(where, "give one of trajectory (the paper's motion 1 or 2) and file (a motion file)")
        motion = {}
        if 'file' in data:
            motion['file'] = self.file(f'{where}.file', data['file'])
            default = Path(motion['file']).stem
        else:
            if isinstance(data['trajectory'], bool) or data['trajectory'] not in PAPER_TRAJECTORIES:
                self.fail(f'{where}.trajectory',
                          f'must be one of {PAPER_TRAJECTORIES}, got {shown(data["trajectory"])}')
            motion['trajectory'] = data['trajectory']
            default = f'trajectory-{data["trajectory"]}'
        if 'duration' in data:
            motion['duration'] = self.number(f'{where}.duration', data['duration'], positive=True)
        return {'name': self.name(f'{where}.name', data.get('name', default)), **motion}

    def scenario(self, where: str, data) -> dict:
        data = self.mapping(where, data, SCENARIO_KEYS)
        scenario = {}
        if 'tau' in data:
            scenario['tau'] = self.number(f'{where}.tau', data['tau'], non_negative=True)
        if 'mass_scale' in data:
            scenario['mass_scale'] = self.numbers(f'{where}.mass_scale', data['mass_scale'], scalar=True,
                                                  positive=True)
        for key in ('external_torque', 'viscous_friction', 'coulomb_friction'):
            if key in data:
                scenario[key] = self.numbers(f'{where}.{key}', data[key])
        if 'name' not in data and scenario:
            self.fail(where, 'a scenario that changes the episode needs a name')
        return {'name': self.name(f'{where}.name', data.get('name', 'nominal')), **scenario}

    def controller(self, where: str, value) -> str:
        return self.choice(where, value, CONTROLLERS)

    def distinct(self, where: str, entries: list[dict]) -> None:
        for name, count in Counter(entry['name'] for entry in entries).items():
            if count > 1:
                self.fail(where, f'the name {shown(name)} is given {count} times')


def load_campaign(path: Path | str) -> Campaign:
    """The campaign file at `path`, read and every job checked; CampaignError names the key or job refused."""
    path = Path(path)
    try:
        text = read_data_file(path)
    except DataFileError as error:
        raise CampaignError(f'{path}: cannot read the campaign file: {error}') from None
    except OSError as error:
        raise CampaignError(f'{path}: cannot read the campaign file: {error}') from error
    return parse_campaign(text, path)


def parse_campaign(text: str, path: Path) -> Campaign:
    """The campaign whose text is `text`; `path` names it in refusals, and relative file paths start from its folder."""
    reader = _Reader(path)
    try:
        document = yaml.load(text, Loader=DataLoader)  # YAML 1.2 numbers, duplicate keys refused (safe)
    except yaml.YAMLError as error:  # on one line, as every refusal
        raise CampaignError(f'{path}: not a YAML file ddarm reads: {" ".join(str(error).split())}') from error
    if document is None:
        raise CampaignError(f'{path}: empty: a campaign lists controllers (with arms, motions, scenarios) and/or jobs')
    if isinstance(document, dict):
        document = renamed_keys(document, TOP_RENAMED, f'{path}: the top level', CampaignError)
    document = reader.mapping('the top level', document, TOP_KEYS)
    description = document.get('description', '')
    if not isinstance(description, str):
        reader.fail('description', f'must be text, got {shown(description)}')
    shared = reader.options('', document)
    if 'controllers' not in document and any(key in document for key in ('arms', 'motions', 'scenarios')):
        reader.fail('controllers', 'arms, motions and scenarios make jobs only with controllers: give controllers')
    if 'controllers' not in document and 'jobs' not in document:
        reader.fail('the top level', 'no jobs: give controllers (with arms, motions and scenarios) and/or jobs')
    parts = []
    listed = reader.items('jobs', document['jobs']) if 'jobs' in document else []
    if 'controllers' in document:
        axes = {key: (reader.items(key, document.get(key, default)), read) for key, read, default in (
            ('arms', reader.arm, [{}]), ('motions', reader.motion, [{'trajectory': 1}]), ('scenarios', reader.scenario,
                                                                                          [{}]))}
        given_controllers = reader.items('controllers', document['controllers'])
        product = len(given_controllers) * math.prod(len(items) for items, _ in axes.values())
        _check_job_count(reader, len(listed) + product)
        for key, (given, read) in axes.items():
            entries = [read(f'{key}[{i}]', item) for i, item in enumerate(given)]
            reader.distinct(key, entries)
            axes[key] = entries
        controllers = [reader.controller(f'controllers[{i}]', law) for i, law in enumerate(given_controllers)]
        if len(set(controllers)) != len(controllers):
            reader.fail('controllers', f'a controller is given twice: {controllers}')
        parts += [(f'the job {arm["name"]}.{motion["name"]}.{law}.{scenario["name"]} (of the product)',
                   None, arm, motion, law, scenario, {})
                  for arm in axes['arms'] for motion in axes['motions'] for law in controllers
                  for scenario in axes['scenarios']]
    _check_job_count(reader, len(listed))
    if 'jobs' in document:
        for i, item in enumerate(listed):
            where = f'jobs[{i}]'
            if isinstance(item, dict):
                item = renamed_keys(item, JOB_RENAMED, f'{path}: {where}', CampaignError)
            item = reader.mapping(where, item, JOB_KEYS)
            if 'controller' not in item:
                reader.fail(where, f'no controller: one of {", ".join(CONTROLLERS)}')
            name = reader.name(f'{where}.name', item['name']) if 'name' in item else None
            parts.append((where, name, reader.arm(f'{where}.arm', item.get('arm', {})),
                          reader.motion(f'{where}.motion', item.get('motion', {'trajectory': 1})),
                          reader.controller(f'{where}.controller', item['controller']),
                          reader.scenario(f'{where}.scenario', item.get('scenario', {})),
                          reader.options(where, item)))
    jobs, warnings, seen = [], [], {}
    for where, name, arm, motion, law, scenario, options in parts:
        job = _job(reader, where, name, arm, motion, law, scenario, {**shared, **options})
        if job.name in seen:
            reader.fail(where, f'its name {shown(job.name)} is also that of {seen[job.name]}: give the job a name')
        if len(job.name) + len(JOB_FILE_SUFFIX) > NAME_MAX:
            reader.fail(where, f'its name {shown(job.name)} ({len(job.name)} characters) names its bag\'s storage '
                               f'file and gains file ({shown(job.name + JOB_FILE_SUFFIX)}), longer than the {NAME_MAX} '
                               'bytes a file name may have: give the job a shorter name')
        seen[job.name] = where
        try:
            warnings += [f'{job.name}: {warning}' for warning in check_episode(job.template).warnings]
            start_kp, start_kv = omega_starts(job.template, job.omegas)
            check_search(job.template, index=job.index, start_kp=start_kp, start_kv=start_kv, budget=job.budget,
                         method=job.method, seed=job.seed)
        except DdarmError as error:
            reader.fail(where, str(error))
        jobs.append(job)
    return Campaign(path, text, description, tuple(jobs), tuple(warnings))


def _check_job_count(reader: _Reader, count: int) -> None:
    if count > MAX_JOBS:
        reader.fail('the top level', f'{count} jobs (arms × motions × controllers × scenarios, and those listed), more '
                                     f'than the {MAX_JOBS} a campaign may run')


def _job(reader: _Reader, where: str, name: str | None, arm: dict, motion: dict, law: str, scenario: dict,
         options: dict) -> CampaignJob:
    """A job's episode and search from its parts; the episode's own refusals name the job."""
    if 'index' not in options:
        reader.fail(where, f'no index: give index ({", ".join(INDICES)}) at the top or in the job')
    plant = {key: value for key, value in scenario.items() if key != 'name'}
    try:
        template = EpisodeSpec(
            controller=law, trajectory=motion.get('trajectory', EPISODE_DEFAULTS['trajectory']),
            duration=motion.get('duration'), urdf=arm.get('urdf'), model_urdf=arm.get('model_urdf'),
            motion=motion.get('file'),
            **{key: options.get(key, EPISODE_DEFAULTS[key]) for key in ('period', 'delay', 'torque_limit',
                                                                          'substeps')},
            **{key: value for key, value in plant.items() if key != 'mass_scale'})
        dof = len(arm_joints(template)[0])
        mass_scale = plant.get('mass_scale')
        if mass_scale is not None and len(mass_scale) == 1:
            mass_scale = mass_scale * dof  # one number scales every link, as `ddarm tune --robust-mass-scale` reads it
        template = dataclasses.replace(template, mass_scale=mass_scale)
    except DdarmError as error:
        reader.fail(where, str(error))
    return CampaignJob(name or f'{arm["name"]}.{motion["name"]}.{law}.{scenario["name"]}', arm['name'],
                       motion['name'], law, scenario['name'], template, options['index'],
                       options.get('method', DEFAULT_METHOD), options.get('budget', DEFAULT_TUNE_BUDGET),
                       options.get('seed', 0), tuple(options.get('omegas', SEARCH_START_OMEGAS)))


class EpisodeRecorder(Protocol):
    """What runs each job's check episode: the ROS graph session, in lockstep."""

    def record_and_score(self, spec: EpisodeSpec, bag: Path, command: str | None = None, storage: str = 'mcap'
                         ) -> tuple[Any, dict]:
        """Run `spec`, record it as a bag at `bag`, and return what ran and the bag's score (`ddarm score --json`)."""


def job_record(job: CampaignJob) -> dict:
    """What defines the job, for summary.json: its parts, its search's options and its episode."""
    # 'law' is the deprecated name of 'controller', kept so that scripts reading summary.json go on working.
    return {'name': job.name, 'arm': job.arm, 'motion': job.motion, 'controller': job.controller,
            'law': job.controller, 'scenario': job.scenario,
            'scenario_values': job.scenario_record,
            'scenario_text': f'{job.scenario}: {describe_scenario(job.template, len(arm_joints(job.template)[0]))}',
            'index': job.index, 'method': job.method, 'budget': job.budget,
            'seed': job.seed, 'omegas': list(job.omegas), 'joint_names': list(arm_joints(job.template)[0])}


def search_record(job: CampaignJob, found: JobSearch) -> dict:
    """The job's record once its search is done: status 'searched' with the search's gains and values (their check
    through the graph still to come), or 'failed' with why the search found no gains."""
    record = job_record(job)
    if found.tuning is None:
        return {**record, 'status': 'failed', 'reason': f'search: {found.error}'}
    tuning = found.tuning
    spec = job.template.with_gains(tuning.search.kp, tuning.search.kv)
    record.update(kp=tuning.search.kp.tolist(), kv=tuning.search.kv.tolist(),
                  gains={name: {'p': p, 'd': d} for name, p, d in zip(record['joint_names'], tuning.search.kp.tolist(),
                                                                     tuning.search.kv.tolist())},
                  search_index=tuning.search.index,
                  in_process={key: tuning.best[key] for key in INDICES}, episodes=tuning.search.episodes,
                  search_wall_time_s=tuning.wall_time_s, warnings=list(tuning.warnings), spec=spec.to_dict(),
                  **tuning.search.certainty_fields(hint=False))
    if tuning.search.certificate is not None:
        record['certificate'] = tuning.search.certificate.to_dict()
    return {**record, 'status': 'searched'}


class StorageFailure(CampaignError):
    """The run folder's file system failed while a job's gains were checked (a full disk, a quota, an I/O error):
    the run's failure, not the job's, as every later job would fail alike. `record` is the job's, failed."""

    def __init__(self, message: str, record: dict) -> None:
        super().__init__(message)
        self.record = record


# What a failing file system says: no space, no quota left, a file too large, read-only, an I/O error.
STORAGE_ERRNOS = frozenset((errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EIO))


def _storage_failed(error: BaseException) -> bool:
    """Whether a failing file system is behind `error` (an OSError of STORAGE_ERRNOS, or sqlite's full disk or
    I/O error, anywhere in its chain of causes)."""
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, OSError) and error.errno in STORAGE_ERRNOS:
            return True
        if isinstance(error, sqlite3.Error) and getattr(error, 'sqlite_errorname', '').startswith(
                ('SQLITE_FULL', 'SQLITE_IOERR')):
            return True
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return False


def check_job(recorder: EpisodeRecorder, run: RunFolder, job: CampaignJob, found: JobSearch,
              storage: str = 'mcap') -> dict:
    """The job's best gains run once through `recorder`, recorded in the run folder and scored from the bag.

    Returns the job's record: the search's value beside the bag's score, and its status, 'ok' only when the
    search found gains, the recorded episode did not diverge and the bag agrees with the search (as `ddarm
    tune` asks before it writes gains, ddarm.tuning.outputs.AGREEMENT); then the gains are written as a
    controller YAML (gains/<job>.yaml). Otherwise 'failed', with the reason.

    Raises:
        StorageFailure: the bag could not be written or read for a failing file system; the unfinished bag is
            removed first (no scorer accepts it, and its space lets the summary say how the run ended).
    """
    record = search_record(job, found)
    if record['status'] == 'failed':
        return record
    tuning = found.tuning
    spec = job.template.with_gains(tuning.search.kp, tuning.search.kv)
    bag = run.bag_path(job.name)
    try:
        _, scored = recorder.record_and_score(spec, bag, command=run.summary['command'], storage=storage)
    except DdarmError as error:
        if not _storage_failed(error):  # a node that died, a bag that cannot be read: this job has no evidence
            return {**record, 'status': 'failed', 'reason': f'graph episode: {error}'}
        run.discard_bag(bag)
        reason = f'graph episode: {error} (its unfinished bag removed)'
        raise StorageFailure(f'{error} (job {job.name}: the campaign stops there, as every later job would fail '
                             'alike; its unfinished bag removed)', {**record, 'status': 'failed', 'reason': reason}
                             ) from error
    difference = relative_difference(tuning.best, scored)
    record.update({key: scored[key] for key in INDICES}, bag_index=scored[job.index],
                  diverged=scored['diverged'], max_rel_difference=difference, agree=difference <= AGREEMENT,
                  bag=str(Path(scored['bag']).relative_to(run.path)),
                  saturated_joints=scored.get('saturated_joints', []))
    if scored['diverged']:
        return {**record, 'status': 'failed',
                'reason': f'the recorded episode diverged at sample {scored["diverged_at"]}'}
    if not record['agree']:
        return {**record, 'status': 'failed',
                'reason': f'the bag disagrees with the search: {job.index} = {scored[job.index]!r} from the bag, '
                          f'{tuning.best[job.index]!r} in-process (relative difference {difference:.2e})'}
    (run.path / 'gains').mkdir(exist_ok=True)
    provenance = (f"campaign job {job.name}: {job.index} = {scored[job.index]!r} (scored from {record['bag']})"
                  f"{search_doubt(tuning.search, hint=False)}\n"
                  f"from: {run.summary['command']}")
    (gains_file,) = write_gains(run, tuning.search.kp, tuning.search.kv, spec, provenance,
                                name=f'gains/{job.name}.yaml')
    return {**record, 'status': 'ok', 'gains_file': str(Path(gains_file).relative_to(run.path))}


class JobRecords:
    """summary.json's `jobs` and `failed` while the campaign runs, rewritten at every change so that a run stopped,
    failed or killed part way still says what finished: in the campaign's order, each job once its search is done
    (search_record: `searched`, or `failed`), then once its gains are checked (check_job: `ok` or `failed`)."""

    def __init__(self, run: RunFolder, campaign: Campaign) -> None:
        self.run, self.campaign, self._by_name = run, campaign, {}
        self._write()

    def add(self, record: dict) -> None:
        """`record` as its job's, in place of what it had; written at once."""
        self._by_name[record['name']] = record
        self._write()

    @property
    def records(self) -> list[dict]:
        return [self._by_name[job.name] for job in self.campaign.jobs if job.name in self._by_name]

    def _write(self) -> None:
        records = self.records
        self.run.summary['failed'] = failed_jobs(records)
        self.run.record('jobs', records)


def check_jobs(recorder: EpisodeRecorder, run: RunFolder, campaign: Campaign, found: dict[str, JobSearch],
               storage: str = 'mcap', on_record=None, records: JobRecords | None = None) -> list[dict]:
    """Every job checked in the campaign's order (check_job), its record in the run's summary (`records`, or new
    ones) as soon as it is made, so that a run stopped part way says which jobs were checked. `on_record(record)`
    is called after each."""
    records = JobRecords(run, campaign) if records is None else records
    for job in campaign.jobs:
        try:
            record = check_job(recorder, run, job, found[job.name], storage)
        except StorageFailure as failure:
            records.add(failure.record)
            raise
        records.add(record)
        if on_record is not None:
            on_record(record)
    return records.records


def failed_jobs(records: list[dict]) -> list[str]:
    return [record['name'] for record in records if record['status'] == 'failed']


def _cell(value) -> str:
    return '–' if value is None else f'{value:.6g}'


def summary_table(campaign: Campaign, records: list[dict]) -> str:
    """SUMMARY.md: one row per job, the search's index beside its bag's, and each failure's reason."""
    lines = [f'# Campaign {markdown_text(campaign.path.name)}', '']
    if campaign.description:
        lines += [markdown_paragraph(campaign.description), '']
    lines += ['Every *bag* number is scored from the job\'s bag (`ddarm score <bag>` recomputes it); *search* is the '
              'value the search found in-process.', '',
              '| job | arm | motion | controller | scenario | index | search | bag | status |',
              '|---|---|---|---|---|---|---|---|---|']
    for record in records:
        bag = f"[{_cell(record['bag_index'])}]({quote(record['bag'])})" if 'bag' in record else '–'
        status = 'ok' if record['status'] == 'ok' else f"**FAILED**: {markdown_text(record['reason'])}"
        cells = (markdown_text(record[key])
                 for key in ('name', 'arm', 'motion', 'controller', 'scenario_text', 'index'))
        doubt = ({False: ' (not converged)', None: ' (not certified)'}.get(record['converged'], '')
                 if 'certainty' in record else '')  # a failed search's record has no verdict
        lines.append('| ' + ' | '.join((*cells, _cell(record.get('search_index')) + doubt, bag, status)) + ' |')
    failed = failed_jobs(records)
    lines += ['', f'{len(records) - len(failed)} of {len(records)} jobs ok'
              + (f"; failed: {markdown_text(', '.join(failed))}" if failed else '') + '.', '']
    doubted = [record for record in records if 'certainty' in record and not record['converged']]
    if doubted:
        lines += ['Searches not sure of their minimum (a larger `budget` is what to try):', '',
                  *(f"- {markdown_text(record['name'])}: {markdown_text(record['certainty'])}" for record in doubted),
                  '']
    lines += [f'![index per job]({PLOT_NAME})', '']
    return '\n'.join(lines)


def index_plot(path: Path, records: list[dict]) -> None:
    """Each job's index as its bag scores it, one bar per job grouped by law (log scale); a failed job's bar is
    missing and labelled FAILED."""
    laws = sorted({record['controller'] for record in records}, key=CONTROLLERS.index)
    ordered = [record for law in laws for record in records if record['controller'] == law]
    figure = Figure(figsize=(max(6.0, 0.6 * len(ordered) + 2.0), 4.8), dpi=110)
    FigureCanvasAgg(figure)
    axis = figure.subplots()
    colours = dict(zip(CONTROLLERS, ('tab:blue', 'tab:orange')))
    scored = [record['bag_index'] for record in ordered if record['status'] == 'ok']
    floor = min(scored) / 10 if scored else 1.0
    for position, record in enumerate(ordered):
        if record['status'] == 'ok':
            axis.bar(position, record['bag_index'], color=colours.get(record['controller'], 'tab:gray'))
        else:
            axis.text(position, floor * 2, 'FAILED', rotation=90, ha='center', va='bottom', color='tab:red')
    for law in laws:
        axis.bar([], [], color=colours.get(law, 'tab:gray'), label=law)
    axis.set_yscale('log')
    axis.set_ylim(bottom=floor)
    axis.set_xticks(range(len(ordered)), [figure_text(f"{record['name']} ({record['index']})") for record in ordered],
                    rotation=60, ha='right', fontsize=7, parse_math=False)
    axis.set_ylabel('index, scored from the bag')
    axis.legend(fontsize=8)
    axis.grid(True, axis='y', alpha=0.3)
    figure.tight_layout()
    write_new_file(path, lambda file: figure.savefig(file, format='png'))


def write_summary(run: RunFolder, campaign: Campaign, records: list[dict]) -> dict:
    """SUMMARY.md and the plot in the run folder, and the run finished: `complete` only if every job is ok.

    Returns the summary (summary.json's content, the JSON `ddarm campaign --json` prints)."""
    run.write_text(TABLE_NAME, summary_table(campaign, records))
    index_plot(run.path / PLOT_NAME, records)
    failed = failed_jobs(records)
    run.finish('complete' if not failed else f'{len(failed)} of {len(records)} jobs failed: {", ".join(failed)}',
               failed=failed, table=TABLE_NAME, plot=PLOT_NAME)
    return json.loads((run.path / SUMMARY_NAME).read_text())
