"""The indices (2.5) and (3.2) with spec §8's weights, on cases small enough to do by hand."""

import dataclasses

import numpy as np
import pytest

from ddarm.episodes.engine import run_episode, simulate_batch
from ddarm.episodes.indices import IndicesError, score_series, torque_weights
from ddarm.episodes.spec import EpisodeSpec


def test_index_2_5_by_hand():
    # Two joints, k_max = 2 (samples j = 0, 1, 2); errors in radians, weighed in degrees.
    errors = np.array([[0.0, 0.0], [np.pi / 180, -2 * np.pi / 180], [0.0, 3 * np.pi / 180]])
    # Σ |e| in degrees = 1 + 2 + 3 = 6; divided by k_max = 2.
    q_ref = np.array([[0.3, -0.2], [0.1, 0.4], [-0.5, 0.0]])
    nominal = np.ones((3, 2))
    indices = score_series(q_ref, q_ref - errors, nominal, nominal, k_max=2)
    assert indices['I1'] == pytest.approx(3.0)


def test_torque_weights_make_ten_percent_of_the_nominal_maximum_weigh_one():
    nominal = np.array([[10.0, -40.0], [-20.0, 5.0]])
    np.testing.assert_allclose(torque_weights(nominal), [10 / 20, 10 / 40])


def test_index_3_2_by_hand():
    nominal = np.array([[10.0, -40.0], [-20.0, 5.0]])
    torques = nominal + np.array([[2.0, 0.0], [0.0, -4.0]])  # 10 % of joint 1's max, 10 % of joint 2's
    errors = np.array([[np.pi / 180, 0.0], [0.0, 0.0]])
    q_ref = np.array([[0.2, 0.1], [-0.3, 0.7]])
    indices = score_series(q_ref, q_ref - errors, torques, nominal, k_max=1)
    total, first, second = indices['I'], indices['I1'], indices['I2']
    assert first == pytest.approx(1.0)
    assert second == pytest.approx(2.0)  # each 10 % deviation weighs as 1°
    assert total == pytest.approx(3.0)


def test_indices_broadcast_over_a_batch():
    # A batch's indices are, member by member, those of the member run alone.
    rng = np.random.default_rng(3)
    kp = 225.0 * np.exp(0.3 * rng.normal(size=(4, 3)))
    kv = 30.0 * np.exp(0.3 * rng.normal(size=(4, 3)))
    template = EpisodeSpec(controller='computed_torque', kp=tuple(kp[0]), kv=tuple(kv[0]), tau=0.1)
    batch = simulate_batch(template, kp, kv)
    assert batch.I1.shape == batch.I2.shape == batch.I.shape == (4,)
    alone = run_episode(dataclasses.replace(template, kp=tuple(kp[2]), kv=tuple(kv[2])))
    for key in ('I1', 'I2', 'I'):
        assert batch.indices(2)[key] == pytest.approx(alone.indices()[key])
    # And the batch's running sums are score_series over the member's recorded samples.
    plan = alone.plan
    scored = score_series(plan.q_ref, alone.scored('q'), alone.scored('torque'), plan.nominal, plan.k_max)
    for key in ('I1', 'I2', 'I'):
        assert scored[key] == pytest.approx(alone.indices()[key], rel=1e-12)


def test_a_joint_without_nominal_torque_cannot_be_weighed():
    with pytest.raises(IndicesError, match='nonzero'):
        torque_weights(np.array([[1.0, 0.0], [2.0, 0.0]]))
