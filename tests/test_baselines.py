"""The ProMP baseline adapter (the algorithm is movement_primitives')."""

import numpy as np
import pytest

from lerobot_cnmp.baselines import ProMPBaseline
from lerobot_cnmp.conditions import Condition


@pytest.fixture(scope="module")
def promp():
    tau = np.linspace(0, 1, 100)
    demos = [np.stack([tau, a * np.sin(np.pi * tau)], 1) for a in np.linspace(0.2, 0.6, 8)]
    return ProMPBaseline(n_weights_per_dim=15).fit(demos)


def test_prediction_passes_through_conditions_at_any_query(promp):
    cond = [Condition(0.5, (0.5, 0.5))]
    one, _ = promp.predict([0.5], cond)  # a single query must not be rescaled to t = 1
    many, std = promp.predict(np.linspace(0, 1, 201), cond)
    np.testing.assert_allclose(one[0], [0.5, 0.5], atol=5e-3)
    np.testing.assert_allclose(many[100], one[0], atol=1e-4)
    assert std[100, 1] < 0.01 and std[0, 1] >= 0


def test_partial_condition_leaves_other_dims_free(promp):
    mean, _ = promp.predict([0.5], [Condition(0.5, (np.nan, 0.3), dims=(1,))])
    assert abs(mean[0, 1] - 0.3) < 5e-3 and abs(mean[0, 0] - 0.5) < 0.05


def test_bad_inputs(promp):
    with pytest.raises(ValueError, match="SM has 2"):
        promp.predict([0.5], [Condition(0.5, (0.5,))])
    with pytest.raises(ValueError, match="outside"):
        promp.predict([0.5], [Condition(1.5, (0.5, 0.1))])
    with pytest.raises(ValueError, match="phases"):
        promp.predict([2.0], [Condition(0.5, (0.5, 0.1))])
    with pytest.raises(RuntimeError, match="not fitted"):
        ProMPBaseline().predict([0.5], [Condition(0.5, (0.5, 0.1))])
