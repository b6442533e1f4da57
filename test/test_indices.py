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


@pytest.mark.parametrize('change, refused', [
    (dict(torque=np.zeros((2, 2))), r'q and torque must have the same shape .*q \(3, 2\), torque \(2, 2\)'),
    (dict(q=np.zeros((4, 2)), torque=np.zeros((4, 2))), r'4 scored samples, more than q_ref and nominal hold'),
    (dict(nominal=np.ones((2, 2))), r'3 scored samples, more than q_ref and nominal hold.*nominal \(2, 2\)'),
    (dict(q=np.zeros((3, 3)), torque=np.zeros((3, 3))), r'the same joint count, got q_ref \(3, 2\), q \(3, 3\)'),
    (dict(nominal=np.ones((3, 3))), r'the same joint count.*nominal \(3, 3\)'),
    (dict(q=np.zeros(3)), r'shape \(samples, joints\), got q_ref \(3, 2\), q \(3,\)'),
])
def test_series_the_compiled_sums_would_read_out_of_bounds_are_refused(change, refused):
    # The compiled loop does no bounds checks: mismatched series are refused by their shapes first.
    series = dict(q_ref=np.zeros((3, 2)), q=np.zeros((3, 2)), torque=np.zeros((3, 2)), nominal=np.ones((3, 2)))
    with pytest.raises(IndicesError, match=refused):
        score_series(**{**series, **change}, k_max=2)


def test_fewer_scored_samples_than_the_reference_are_scored():
    q_ref, nominal = np.zeros((3, 2)), np.ones((3, 2))
    indices = score_series(q_ref, q_ref[:1] - np.pi / 180, nominal[:1], nominal, k_max=2)
    assert indices['I1'] == pytest.approx(1.0)
