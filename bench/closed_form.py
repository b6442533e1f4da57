"""The batch engine against a hand-written closed-form loop for the paper's arm, side by side (issue 13).

    .venv/bin/python bench/closed_form.py [--episodes 1000] [--rounds 5] [--json]

The closed-form loop is what a control engineer would write for this one arm and nothing else:
M(q), V(q, q̇) and G(q) of docs/model-specification.md §3 as formulas (V from M's Christoffel symbols), the 2x2
block solved by hand, computed torque with delay 1, RK4 with the engine's substeps, the
divergence bounds and the indices (2.5) and (3.2); numba `prange` over the episodes on every
core. It runs the engine's reference episode (ddarm.episodes.bench.REFERENCE) with the same
perturbed gains, and both must agree on every index before their rates are compared. The two are
timed in alternation, round after round, and the best round of each is reported: this machine's
speed varies by tens of percent from minute to minute, the ratio much less.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numba
import numpy as np

from ddarm.episodes.bench import REFERENCE, perturbed_gains
from ddarm.episodes.engine import simulate_batch
from ddarm.episodes.indices import error_weights, torque_weights
from ddarm.episodes.spec import check_episode
from ddarm.physics.plant import DEFAULT_MAX_POSITION, DEFAULT_MAX_VELOCITY

G = 9.81


@numba.njit(inline='always', fastmath={'contract'})
def _dynamics(q1, q2, q3, v1, v2, v3):
    """M11, the lower 2x2 block of M (M12 = M13 = 0), V and G of docs/model-specification.md §3 at one state."""
    c2, s2, c3, s3 = np.cos(q2), np.sin(q2), np.cos(q3), np.sin(q3)
    c23, s23 = np.cos(q2 + q3), np.sin(q2 + q3)
    reach = c2 + 0.5 * c23
    m11 = 1.0 + 3.5 * c2 * c2 + 10.0 * reach * reach + c23 * c23
    m22, m23, m33 = 17.0 + 10.0 * c3, 3.5 + 5.0 * c3, 3.5
    dm11_2 = -7.0 * c2 * s2 - 20.0 * reach * (s2 + 0.5 * s23) - 2.0 * c23 * s23
    dm11_3 = -10.0 * reach * s23 - 2.0 * c23 * s23
    bias1 = v1 * (dm11_2 * v2 + dm11_3 * v3)
    bias2 = -0.5 * dm11_2 * v1 * v1 - 10.0 * s3 * v2 * v3 - 5.0 * s3 * v3 * v3 + G * (5.0 * c2 + 10.0 * reach)
    bias3 = -0.5 * dm11_3 * v1 * v1 + 5.0 * s3 * v2 * v2 + 5.0 * G * c23
    return m11, m22, m23, m33, bias1, bias2, bias3


@numba.njit(inline='always', fastmath={'contract'})
def _acceleration(q1, q2, q3, v1, v2, v3, p1, p2, p3):
    m11, m22, m23, m33, b1, b2, b3 = _dynamics(q1, q2, q3, v1, v2, v3)
    r2, r3 = p2 - b2, p3 - b3
    det = m22 * m33 - m23 * m23
    return (p1 - b1) / m11, (m33 * r2 - m23 * r3) / det, (m22 * r3 - m23 * r2) / det


@numba.njit(parallel=True, fastmath={'contract'})
def closed_form_batch(kp, kv, q0, v0, q_ref, v_ref, a_ref, nominal, error_weight, torque_weight, period, substeps,
                      max_position, max_velocity):
    """I1 and I2 sums of computed torque with delay 1 for each episode's gains (rows of kp, kv): every state a
    scalar, as one writes it for one arm."""
    size, samples = kp.shape[0], q_ref.shape[0]
    error_sum, torque_sum = np.zeros(size), np.zeros(size)
    h = period / substeps
    for b in numba.prange(size):
        q1, q2, q3 = q0[0], q0[1], q0[2]
        v1, v2, v3 = v0[b, 0], v0[b, 1], v0[b, 2]
        m_q1, m_q2, m_q3, m_v1, m_v2, m_v3 = q1, q2, q3, v1, v2, v3  # the state the next torque is computed from
        first, second = 0.0, 0.0
        for k in range(samples):
            j = k - 1 if k >= 1 else 0
            u1 = a_ref[k, 0] + kp[b, 0] * (q_ref[j, 0] - m_q1) + kv[b, 0] * (v_ref[j, 0] - m_v1)
            u2 = a_ref[k, 1] + kp[b, 1] * (q_ref[j, 1] - m_q2) + kv[b, 1] * (v_ref[j, 1] - m_v2)
            u3 = a_ref[k, 2] + kp[b, 2] * (q_ref[j, 2] - m_q3) + kv[b, 2] * (v_ref[j, 2] - m_v3)
            m11, m22, m23, m33, b1, b2, b3 = _dynamics(m_q1, m_q2, m_q3, m_v1, m_v2, m_v3)
            p1, p2, p3 = m11 * u1 + b1, m22 * u2 + m23 * u3 + b2, m23 * u2 + m33 * u3 + b3
            first += (abs(q_ref[k, 0] - q1) * error_weight[0] + abs(q_ref[k, 1] - q2) * error_weight[1]
                      + abs(q_ref[k, 2] - q3) * error_weight[2])
            second += (abs(p1 - nominal[k, 0]) * torque_weight[0] + abs(p2 - nominal[k, 1]) * torque_weight[1]
                       + abs(p3 - nominal[k, 2]) * torque_weight[2])
            if k == samples - 1:
                break
            m_q1, m_q2, m_q3, m_v1, m_v2, m_v3 = q1, q2, q3, v1, v2, v3
            x1, x2, x3, y1, y2, y3 = q1, q2, q3, v1, v2, v3
            for _ in range(substeps):
                a1, a2, a3 = _acceleration(x1, x2, x3, y1, y2, y3, p1, p2, p3)
                e1, e2, e3 = y1 + 0.5 * h * a1, y2 + 0.5 * h * a2, y3 + 0.5 * h * a3
                c1, c2, c3 = _acceleration(x1 + 0.5 * h * y1, x2 + 0.5 * h * y2, x3 + 0.5 * h * y3, e1, e2, e3,
                                           p1, p2, p3)
                f1, f2, f3 = y1 + 0.5 * h * c1, y2 + 0.5 * h * c2, y3 + 0.5 * h * c3
                d1, d2, d3 = _acceleration(x1 + 0.5 * h * e1, x2 + 0.5 * h * e2, x3 + 0.5 * h * e3, f1, f2, f3,
                                           p1, p2, p3)
                g1, g2, g3 = y1 + h * d1, y2 + h * d2, y3 + h * d3
                r1, r2, r3 = _acceleration(x1 + h * f1, x2 + h * f2, x3 + h * f3, g1, g2, g3, p1, p2, p3)
                x1 += h / 6.0 * (y1 + 2.0 * e1 + 2.0 * f1 + g1)
                x2 += h / 6.0 * (y2 + 2.0 * e2 + 2.0 * f2 + g2)
                x3 += h / 6.0 * (y3 + 2.0 * e3 + 2.0 * f3 + g3)
                y1 += h / 6.0 * (a1 + 2.0 * c1 + 2.0 * d1 + r1)
                y2 += h / 6.0 * (a2 + 2.0 * c2 + 2.0 * d2 + r2)
                y3 += h / 6.0 * (a3 + 2.0 * c3 + 2.0 * d3 + r3)
            inside = True
            for x in (x1, x2, x3):
                inside = inside and np.isfinite(x) and abs(x) <= max_position
            for y in (y1, y2, y3):
                inside = inside and np.isfinite(y) and abs(y) <= max_velocity
            if not inside:
                break
            q1, q2, q3, v1, v2, v3 = x1, x2, x3, y1, y2, y3
        error_sum[b], torque_sum[b] = first, second
    return error_sum, torque_sum


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--episodes', type=int, default=1000)
    parser.add_argument('--rounds', type=int, default=5)
    parser.add_argument('--json', action='store_true')
    options = parser.parse_args()
    template = REFERENCE
    plan = check_episode(template)
    kp, kv = perturbed_gains(template, options.episodes, seed=0)
    v0 = np.tile(plan.v0, (options.episodes, 1))
    arrays = (np.ascontiguousarray(plan.q0, dtype=float), v0, plan.q_ref, plan.v_ref, plan.a_ref, plan.nominal,
              error_weights(3), torque_weights(plan.nominal))

    def closed_form():
        return closed_form_batch(kp, kv, *arrays, template.period, template.substeps, DEFAULT_MAX_POSITION,
                                 DEFAULT_MAX_VELOCITY)

    def engine():
        return simulate_batch(template, kp, kv, plan=plan)

    first, second = closed_form()  # compiled here, before any timing
    episodes = engine()
    largest = max(np.max(np.abs(first / plan.k_max - episodes.I1) / episodes.I1),
                  np.max(np.abs(second / plan.k_max - episodes.I2) / episodes.I2))
    if not largest <= 1e-9:
        raise SystemExit(f'the closed-form loop and the engine disagree: largest relative index difference {largest:.3g}')
    best = {'closed_form': np.inf, 'ddarm': np.inf}
    for _ in range(options.rounds):
        for name, run in (('closed_form', closed_form), ('ddarm', engine)):
            started = time.perf_counter()
            run()
            best[name] = min(best[name], time.perf_counter() - started)
    rates = {name: options.episodes / seconds for name, seconds in best.items()}
    figures = {
        'case': 'computed torque, ω = 15 gains perturbed (ddarm bench), trajectory 1, T = 1 s, Δ = 0.01 s, delay 1',
        'episodes': options.episodes, 'substeps': template.substeps, 'rounds': options.rounds,
        'cores': len(os.sched_getaffinity(0)), 'max_rel_index_diff': float(largest),
        'closed_form_episodes_per_s': rates['closed_form'], 'ddarm_episodes_per_s': rates['ddarm'],
        'ratio': rates['ddarm'] / rates['closed_form'],
    }
    if options.json:
        print(json.dumps(figures))
    else:
        print(f"{figures['case']}, B = {options.episodes}, RK4 x {template.substeps}, {figures['cores']} cores, "
              f"best of {options.rounds} alternating rounds")
        print(f"  closed-form loop  {rates['closed_form']:9.0f} episodes/s")
        print(f"  ddarm engine      {rates['ddarm']:9.0f} episodes/s   ratio {figures['ratio']:.2f}")
        print(f"  largest relative index difference {largest:.1e}")


if __name__ == '__main__':
    main()
