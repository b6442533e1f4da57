"""The indices (2.5) and (3.2) with MODEL.md section 8's weights, on cases small enough to do by hand."""

import numpy as np
import pytest

from ddarm.episodes.indices import IndicesError, index_2_5, index_3_2, torque_weights


def test_index_2_5_by_hand():
    # Two joints, k_max = 2 (samples j = 0, 1, 2); errors in radians, weighed in degrees.
    errors = np.array([[0.0, 0.0], [np.pi / 180, -2 * np.pi / 180], [0.0, 3 * np.pi / 180]])
    # Σ |e| in degrees = 1 + 2 + 3 = 6; divided by k_max = 2.
    assert index_2_5(errors, k_max=2) == pytest.approx(3.0)


def test_torque_weights_make_ten_percent_of_the_nominal_maximum_weigh_one():
    nominal = np.array([[10.0, -40.0], [-20.0, 5.0]])
    np.testing.assert_allclose(torque_weights(nominal), [10 / 20, 10 / 40])


def test_index_3_2_by_hand():
    nominal = np.array([[10.0, -40.0], [-20.0, 5.0]])
    torques = nominal + np.array([[2.0, 0.0], [0.0, -4.0]])  # 10 % of joint 1's max, 10 % of joint 2's
    errors = np.array([[np.pi / 180, 0.0], [0.0, 0.0]])
    total, first, second = index_3_2(errors, torques, nominal, k_max=1)
    assert first == pytest.approx(1.0)
    assert second == pytest.approx(2.0)  # each 10 % deviation weighs as 1°
    assert total == pytest.approx(3.0)


def test_indices_broadcast_over_a_batch():
    rng = np.random.default_rng(3)
    errors = rng.normal(size=(4, 11, 3))
    batch = index_2_5(errors, k_max=10)
    assert batch.shape == (4,)
    assert batch[2] == pytest.approx(index_2_5(errors[2], k_max=10))


def test_a_joint_without_nominal_torque_cannot_be_weighed():
    with pytest.raises(IndicesError, match='nonzero'):
        torque_weights(np.array([[1.0, 0.0], [2.0, 0.0]]))
