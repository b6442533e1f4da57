"""The episode engine: B closed-loop episodes of one template in one call; one episode is a batch of one.

The loop (spec §5) is assembled here from the one definition of each piece: the delay and
the laws (ddarm.control.laws), the actuators' saturation and the sampled plant step
(ddarm.physics.plant), and the indices (ddarm.episodes.indices). The whole episode is compiled,
and the members are shared out over the cores; why compiled loops, see ddarm.physics.dynamics.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ddarm.arrays import per_episode
from ddarm.control.laws import CONTROLLERS, LAWS, GainError, checked_gains, gravity_feedforward, law_command, measured_sample
from ddarm.control.laws import warm_up as laws_warm_up
from ddarm.episodes.indices import accumulate, error_weights, score_series, torque_weights
from ddarm.episodes.result import Episodes
from ddarm.episodes.spec import (EpisodeError, EpisodePlan, EpisodeSpec, check_episode, episode_robot, model_arm,
                                  model_chain, plan_episode, plant_chain, plant_options)
from ddarm.episodes.stepwise import run_stepwise
from ddarm.errors import DdarmError
from ddarm.motion.programmed import MotionError, disturbed_start
from ddarm.physics.dynamics import cached_njit, compiled_dynamics, load_chain
from ddarm.physics.generated import UNROLLED_JOINTS, VECTOR_LANES
from ddarm.physics.mujoco_plant import MujocoPlant, RobotError
from ddarm.physics.plant import PlantError, advance, checked_mass_scale, saturate, step_workspace
from ddarm.physics.plant import warm_up as plant_warm_up

# Far beyond any batch an optimiser asks for; refused before anything is allocated.
MAX_BATCH = 100_000
# The optional time series are four float arrays of B x (k_max + 1) x n values each.
MAX_SERIES_VALUES = 25_000_000
# Members one thread advances together (see ddarm.physics.dynamics); measured best near 32 here.
LANES = 32
MAX_THREADS = 256
# On the arms whose members run as SIMD vectors (see VECTOR_JOINTS) a batch shares out across threads as soon as it
# needs a second vector: each thread then runs whole vectors (its share padded, see PAD_FROM). Measured side by side
# (bench/thread_share.py, one thread against two, 2026-12-07): on the paper's arm (best of 41) 8 members took 1.16 ms
# against 1.34 ms, 9 took 1.46 against 1.40, 12 took 2.00 against 1.35, 16 1.97 against 1.33, 24 2.73 against 2.19,
# 32 3.55 against 2.18; on the Panda (best of 21) 8 members 4.06 ms against 4.38 ms, 9 5.56 against 4.47, 10 6.91
# against 4.41.
# (Until then the arms of up to 4 joints shared out only from 16 members per thread, from a run whose timings the
# machine's load had spread.) The looped chains beyond VECTOR_JOINTS run one member at a time and share out from
# MIN_MEMBERS_PER_THREAD_UNVECTORISED members per thread (the Panda's did too, before its lanes ran as vectors:
# 8 members 9.87 ms against 5.71 ms).
MIN_MEMBERS_PER_THREAD_UNVECTORISED = 4
# On arms of up to VECTOR_JOINTS joints (those whose dynamics are unrolled, see ddarm.physics.generated) the
# generated dynamics run VECTOR_LANES members at a time in SIMD registers and the members left over one by one, each
# at about 2 to 3 times the cost (measured on the paper's arm: 7 members took 2.18 ms, 8 took 1.28 ms; the same on
# the SCARA; on the Panda 7 members 9.60 ms, 8 4.19 ms). There a chunk with PAD_FROM or more members left over runs a
# whole vector instead, the spare lanes repeating its last member; their results are dropped (Panda: 4 members took
# 5.90 ms, 4.41 ms padded; 3 members 4.81 ms, a whole vector 4.2-4.4 ms; 2 members 3.32 ms). Each member's
# arithmetic is the same in either path, to the last bit.
VECTOR_JOINTS = UNROLLED_JOINTS
PAD_FROM = 4


class BatchError(DdarmError, ValueError):
    """Batch inputs the engine refuses."""


_default_threads: int | None = None  # None: the cores this process may use


def _check_threads(threads) -> None:
    if threads is not None and not (isinstance(threads, (int, np.integer)) and 1 <= threads <= MAX_THREADS):
        raise BatchError(f'threads must be a whole number in [1, {MAX_THREADS}], got {threads!r}')


def set_default_threads(threads: int | None) -> None:
    """The threads a batch runs on when its caller names none: a worker process's share of the cores (None: all)."""
    global _default_threads
    _check_threads(threads)
    _default_threads = None if threads is None else int(threads)


_thread_pools: dict[int, ThreadPoolExecutor] = {}
_thread_pools_lock = threading.Lock()


def _thread_pool(threads: int) -> ThreadPoolExecutor:
    """The pool of `threads` threads every batch of that many threads runs on, kept for the process's life: a
    search makes hundreds of batch calls, and starting the threads anew for each was a cost of its own."""
    with _thread_pools_lock:
        if threads not in _thread_pools:
            _thread_pools[threads] = ThreadPoolExecutor(threads, thread_name_prefix='ddarm-batch')
        return _thread_pools[threads]


@cached_njit()
def _run_chunk(start, lanes, plant_dynamics, model_dynamics, controller, delay, q0, members, episode, plant, record,
               series, outcome):
    """Members start … start + lanes - 1 through the loop of spec §5, all samples in step.

    Each member has its own gains, q̇(0), torque limit and plant mass scale; a member stops at a
    non-finite command for sample n (scored up to n - 1) or a state out of bounds after the
    period from sample n (scored up to n), while the others go on. `plant_dynamics` is the plant's
    forward dynamics, `model_dynamics` the controller model's inverse dynamics (Dynamics).
    """
    plant_scale, member_kp, member_kv, member_v0, member_limit = members
    q_ref, v_ref, a_ref, gravity_ref, nominal, error_weight, torque_weight, viscous_model, coulomb_model = episode
    out_q, out_v, out_command, out_torque = series
    error_sum, torque_sum, diverged_at, scored = outcome
    # Every compiled call counts references to its array arguments: arrays shared with the
    # other threads would have their counts' cache lines bounce between the cores.
    plant = (plant[0].copy(), plant[1].copy(), plant[2].copy(), plant[3], plant[4], plant[5], plant[6])
    n, samples = q0.shape[0], q_ref.shape[0]
    k_max = samples - 1
    scale, kp, kv, limit = np.empty((n, lanes)), np.empty((n, lanes)), np.empty((n, lanes)), np.empty((n, lanes))
    q, v = np.empty((n, lanes)), np.empty((n, lanes))
    for b in range(lanes):
        for i in range(n):
            scale[i, b], limit[i, b] = plant_scale[start + b, i], member_limit[start + b, i]
            kp[i, b], kv[i, b] = member_kp[start + b, i], member_kv[start + b, i]
            q[i, b], v[i, b] = q0[i], member_v0[start + b, i]
    model_scale = np.ones((n, lanes))
    scratch = step_workspace(n, lanes)
    ring_q, ring_v = np.empty((delay + 1, n, lanes)), np.empty((delay + 1, n, lanes))
    commanded_acceleration, command = np.empty((n, lanes)), np.empty((n, lanes))
    applied = np.zeros((n, lanes))
    within = np.ones(lanes, dtype=np.bool_)
    first, second = np.zeros(lanes), np.zeros(lanes)
    running = np.ones(lanes, dtype=np.bool_)
    remaining = lanes
    for b in range(lanes):
        scored[start + b], diverged_at[start + b] = samples, -1
    for k in range(samples):
        ring_q[k % (delay + 1)], ring_v[k % (delay + 1)] = q, v
        measured = measured_sample(k, delay)
        qm, vm = ring_q[measured % (delay + 1)], ring_v[measured % (delay + 1)]
        law_command(controller, model_dynamics, model_scale, kp, kv, q_ref[measured], v_ref[measured], a_ref[k],
                    gravity_ref[k], qm, vm, viscous_model, coulomb_model, commanded_acceleration, command, lanes)
        saturate(command, limit, applied, lanes)
        for b in range(lanes):
            if not running[b]:
                continue
            finite = True
            for i in range(n):
                finite = finite and np.isfinite(command[i, b])
            if not finite:
                diverged_at[start + b], scored[start + b] = k, k
                running[b] = False
                remaining -= 1
                continue
            accumulate(q_ref[k], q, applied, nominal[k], error_weight, torque_weight, first, second, b)
            if record:
                for i in range(n):
                    out_q[start + b, k, i], out_v[start + b, k, i] = q[i, b], v[i, b]
                    out_command[start + b, k, i], out_torque[start + b, k, i] = command[i, b], applied[i, b]
        if remaining == 0 or k == k_max:
            break
        advance(plant_dynamics, scale, plant, applied, q, v, within, scratch, lanes)
        for b in range(lanes):
            if running[b] and not within[b]:
                diverged_at[start + b], scored[start + b] = k + 1, k + 1
                running[b] = False
                remaining -= 1
    for b in range(lanes):
        error_sum[start + b], torque_sum[start + b] = first[b], second[b]


@cached_njit(nogil=True)
def _run_chunks(first_chunk, chunk_stride, lanes, plant_dynamics, model_dynamics, controller, delay, q0, members,
                episode, plant, record, series, outcome):
    """One thread's share of the batch: chunks first_chunk, first_chunk + chunk_stride, … of `lanes` members."""
    size = members[1].shape[0]
    for chunk in range(first_chunk, (size + lanes - 1) // lanes, chunk_stride):
        start = chunk * lanes
        _run_chunk(start, min(lanes, size - start), plant_dynamics, model_dynamics, controller, delay, q0, members,
                   episode, plant, record, series, outcome)


def _shares(size: int, dof: int) -> int:
    """The most threads a batch of `size` members of a `dof`-joint arm shares out over (see VECTOR_LANES)."""
    if dof <= VECTOR_JOINTS:
        return -(-size // VECTOR_LANES)
    return max(1, size // MIN_MEMBERS_PER_THREAD_UNVECTORISED)


def _padded(width: int) -> int:
    """A chunk's lanes, its leftover members rounded up to a whole vector where that is cheaper."""
    left = width % VECTOR_LANES
    return width + (VECTOR_LANES - left if left >= PAD_FROM else 0)


def _chunk_layout(size: int, lanes: int, dof: int) -> tuple[int, np.ndarray | None, np.ndarray | None]:
    """The lanes of each chunk of `size` members cut into chunks of `lanes`, padded (see VECTOR_LANES): (padded
    lanes, the member each padded lane runs, the padded lane of each member), or (lanes, None, None) if no chunk
    gains from padding."""
    padded_lanes, chunks = _padded(lanes), -(-size // lanes)
    last = size - (chunks - 1) * lanes
    if dof > VECTOR_JOINTS or (padded_lanes == lanes and _padded(last) == last):
        return lanes, None, None
    widths = np.full(chunks, lanes)
    widths[-1] = last
    spans = np.full(chunks, padded_lanes)  # each chunk's lanes once padded
    spans[-1] = _padded(last)
    runs = np.concatenate([lanes * number + np.minimum(np.arange(span), width - 1)
                           for number, (width, span) in enumerate(zip(widths, spans))])
    lane_of = np.concatenate([padded_lanes * number + np.arange(width) for number, width in enumerate(widths)])
    return padded_lanes, runs, lane_of


def _batch_gains(kp, kv, dof: int) -> tuple[np.ndarray, np.ndarray]:
    kp, kv = per_episode('kp', kp, None, dof, BatchError), per_episode('kv', kv, None, dof, BatchError)
    if kp.shape != kv.shape:
        raise BatchError(f'kp and kv must have the same shape, got {kp.shape} and {kv.shape}')
    if not 1 <= kp.shape[0] <= MAX_BATCH:
        raise BatchError(f'the batch must hold 1 to {MAX_BATCH} episodes, got B = {kp.shape[0]}')
    return kp, kv


def _initial_velocities(plan: EpisodePlan, tau, size: int) -> np.ndarray:
    """q̇(0) per member: the plan's, or the disturbance (3.1) of the plan's motion at each member's τ."""
    if tau is None:
        return np.broadcast_to(plan.v0, (size, len(plan.v0)))
    tau = np.array(tau, dtype=float)
    if tau.shape != (size,):
        raise BatchError(f'tau must have shape ({size},): one τ per episode, got shape {tau.shape}')
    if plan.motion is None:
        raise BatchError('per-episode tau needs the plan\'s programmed motion: this plan (read back from a '
                         'recording) has none')
    try:
        return disturbed_start(plan.motion, tau)[1]
    except MotionError as error:
        raise BatchError(str(error)) from error


class BatchRunner:
    """The batches of one template: everything that depends on the template and its plan alone (the chains, the
    compiled dynamics, the reference's gravity, the weights) is done once here, so that a search's many small
    batches spend their time in the episodes (a batch of 8 on the Panda spent about 4 ms preparing them anew).

    Calling it runs one batch (see simulate_batch, which is a runner used once). Raises BatchError (a ValueError)
    naming the problem, before anything is simulated.
    """

    def __init__(self, template: EpisodeSpec, plan: EpisodePlan | None = None) -> None:
        if template.mjcf is not None:
            raise BatchError(f'the batch engine runs ddarm\'s own plant; the MJCF robot {template.mjcf} runs one '
                             'episode at a time (ddarm episode --mjcf, ddarm validate)')
        plan = plan if plan is not None else plan_episode(template)
        chain, model = plant_chain(template), model_chain(template)
        dof = chain.dof
        if plan.q_ref.shape[1] != dof:
            raise BatchError(f'the plan has {plan.q_ref.shape[1]} joints, the URDF {dof}')
        try:
            options = plant_options(template, plan, dof)
            if template.mass_scale is not None:
                checked_mass_scale(template.mass_scale, dof)
        except PlantError as error:
            raise BatchError(str(error)) from error
        self.template, self.plan, self.dof = template, plan, dof
        self.torque_limit = options.torque_limit if options.torque_limit is not None else np.full(dof, np.inf)
        self.mass_scale = np.array(template.mass_scale if template.mass_scale is not None else np.ones(dof),
                                   dtype=float)
        zero = np.zeros(dof)
        law = LAWS[template.controller]
        gravity_ref = (gravity_feedforward(model_arm(template), plan.q_ref) if law.gravity_feedforward
                       else np.zeros_like(plan.q_ref))
        # The controller's model of friction F̂: its URDF's <dynamics> and the plant's friction beyond its URDF's
        # (spec §5).
        viscous_model, coulomb_model = (model.joint_friction(template.viscous_friction, template.coulomb_friction)
                                        if law.model_friction else (zero, zero))
        episode = tuple(np.ascontiguousarray(array, dtype=float) for array in (
            plan.q_ref, plan.v_ref, plan.a_ref, gravity_ref, plan.nominal, error_weights(dof),
            torque_weights(plan.nominal), viscous_model, coulomb_model))
        self._fixed = (compiled_dynamics(chain).forward_dynamics, compiled_dynamics(model).inverse_dynamics,
                       law.code, int(template.delay), np.array(plan.q0, dtype=float))
        self._episode, self._plant = episode, options.compiled(chain)
        self.samples = len(plan.times)

    def __call__(self, kp, kv, *, tau=None, torque_limit=None, mass_scale=None, series: bool = False,
                 threads: int | None = None) -> Episodes:
        """B episodes, member b with gains kp[b], kv[b] (shape (B, n) each) and the per-member variations given
        (see simulate_batch)."""
        dof, plan = self.dof, self.plan
        kp, kv = _batch_gains(kp, kv, dof)
        size = kp.shape[0]
        _check_threads(threads)
        v0 = np.array(_initial_velocities(plan, tau, size), dtype=float, order='C')
        varied = {}
        if tau is not None:
            varied['tau'] = np.array(tau, dtype=float)
        if torque_limit is not None:
            limit = varied['torque_limit'] = per_episode('torque_limit', torque_limit, size, dof, BatchError)
        else:
            limit = np.tile(self.torque_limit, (size, 1))
        if mass_scale is not None:
            scale = varied['mass_scale'] = per_episode('mass_scale', mass_scale, size, dof, BatchError)
        else:
            scale = np.tile(self.mass_scale, (size, 1))
        samples = self.samples
        if series and size * samples * dof > MAX_SERIES_VALUES:
            raise BatchError(f'the series of {size} episodes of {samples} samples would hold '
                             f'{size * samples * dof} values per array, more than {MAX_SERIES_VALUES}: '
                             f'ask for fewer episodes or no series')
        if threads is None:
            threads = _default_threads if _default_threads is not None else len(os.sched_getaffinity(0))
        threads = min(threads, _shares(size, dof))
        # As few chunks per thread as chunks of at most LANES allow, and all about one size, so that the
        # threads finish together: 90 members on 2 threads run as 23 + 23 and 23 + 21 (each padded to 24), not
        # 32 + 32 and 26.
        chunks_per_thread = -(-size // (threads * LANES))
        lanes, runs, lane_of = _chunk_layout(size, -(-size // (threads * chunks_per_thread)), dof)
        members = (scale, kp, kv, v0, limit)
        if runs is not None:
            members = tuple(np.ascontiguousarray(array[runs]) for array in members)
        lanes_run = len(members[1])
        series_shape = (lanes_run, samples, dof) if series else (0, samples, dof)
        out_q, out_v, out_command, out_torque = (np.full(series_shape, np.nan) for _ in range(4))
        outcome = (np.zeros(lanes_run), np.zeros(lanes_run), np.zeros(lanes_run, dtype=np.int64),
                   np.zeros(lanes_run, dtype=np.int64))
        arguments = (lanes, *self._fixed, members, self._episode, self._plant, series,
                     (out_q, out_v, out_command, out_torque), outcome)
        if threads == 1:
            _run_chunks(0, 1, *arguments)
        else:
            # The compiled loop releases the GIL: plain threads share the chunks out, interleaved.
            list(_thread_pool(threads).map(lambda first: _run_chunks(first, threads, *arguments), range(threads)))
        if lane_of is not None:
            outcome = tuple(array[lane_of] for array in outcome)
            if series:
                out_q, out_v, out_command, out_torque = (array[lane_of] for array in (out_q, out_v, out_command,
                                                                                      out_torque))
        error_sum, torque_sum, diverged_at, scored = outcome
        first, second = error_sum / plan.k_max, torque_sum / plan.k_max
        return Episodes(template=self.template, plan=plan, kp=kp, kv=kv, I1=first, I2=second, I=first + second,
                        diverged_at=diverged_at, samples_scored=scored, varied=varied,
                        **(dict(q=out_q, v=out_v, command=out_command, torque=out_torque) if series else {}))


def simulate_batch(template: EpisodeSpec, kp, kv, *, tau=None, torque_limit=None, mass_scale=None,
                   series: bool = False, plan: EpisodePlan | None = None,
                   threads: int | None = None) -> Episodes:
    """B episodes of `template` in one call, member b with gains kp[b], kv[b] (shape (B, n) each).

    Every member is the episode `template` with kp, kv replaced by the member's (spec §5–8:
    the zero-order hold, P_n from the state of sample n - d, saturation, divergence, the indices
    (2.5) and (3.2)). Optional per-member variations, each one row per member, replace the
    template's: `tau` (B,) the disturbance (3.1), `torque_limit` (B, n) the actuator limits,
    `mass_scale` (B, n) the plant's link masses against the controller's model. `series` also
    returns q, q̇, the commanded and the applied torque at every sample. `plan` (as from
    plan_episode or plan_motion) saves re-planning; a caller that runs many batches of one template keeps a
    BatchRunner instead, which also keeps the rest of the preparation. Per-member τ disturbs the plan's own
    motion. `threads` (default: the cores this process may use, or set_default_threads's) run the members in
    parallel.

    Raises BatchError (a ValueError) naming the problem, before anything is simulated.
    """
    return BatchRunner(template, plan)(kp, kv, tau=tau, torque_limit=torque_limit, mass_scale=mass_scale,
                                       series=series, threads=threads)


def run_episode(spec: EpisodeSpec, plan: EpisodePlan | None = None) -> Episodes:
    """One episode in-process (spec §5), with its series: a batch of one, or on an MJCF robot (spec.mjcf) the
    stepwise loop against MuJoCo."""
    if spec.is_template:
        raise EpisodeError('an episode template has no gains to run with: give it its gains (with_gains)')
    plan = plan if plan is not None else check_episode(spec)
    try:
        kp, kv = checked_gains(spec.kp, spec.kv, plan.q_ref.shape[1])
    except GainError as error:
        raise EpisodeError(str(error)) from error
    if spec.mjcf is not None:
        try:
            robot = MujocoPlant(episode_robot(spec, plan), plan.q0, plan.v0, plan.torque_limit)
        except RobotError as error:
            raise EpisodeError(str(error)) from error
        return run_stepwise(spec, plan, robot)
    return simulate_batch(spec, [kp], [kv], series=True, plan=plan, threads=1)


def warm_up() -> float:
    """Compile every compiled piece of the loop, or load it from numba's cache, and return the seconds it took.

    The compiled code is written to ddarm's cache (ddarm.physics.dynamics.cache_folder) once; a process that starts
    node processes calls this first, so that a fresh checkout's nodes load it instead of each compiling it at start-up.
    """
    started = time.perf_counter()
    chain = load_chain(None)
    plant_warm_up(chain)
    laws_warm_up(chain)
    spec = EpisodeSpec(controller='computed_torque', kp=(1.0,) * chain.dof, kv=(1.0,) * chain.dof)
    for controller in CONTROLLERS:
        episode = run_episode(dataclasses.replace(spec, controller=controller))
        score_series(episode.plan.q_ref, episode.scored('q'), episode.scored('torque'), episode.plan.nominal,
                     episode.plan.k_max)
    return time.perf_counter() - started
