"""The ProMP and DMP baseline adapters (the algorithms are movement_primitives')."""

import numpy as np
import pytest

from lerobot_cnmp.promp.baselines import DMPBaseline, ProMPBaseline
from lerobot_cnmp.execution.conditions import Condition


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


def test_dmp_reaches_new_start_and_goal_with_the_demos_shape():
    tau = np.linspace(0, 1, 100)
    demos = [np.stack([tau, a * np.sin(np.pi * tau)], 1) for a in np.linspace(0.4, 0.6, 5)]
    dmp = DMPBaseline(n_weights_per_dim=20).fit(demos)
    same, std = dmp.predict(tau, [Condition(0.0, (0.0, 0.0)), Condition(1.0, (1.0, 0.0))])
    np.testing.assert_allclose(same[:, 1], 0.5 * np.sin(np.pi * tau), atol=0.05)  # the mean demo (from rest)
    assert not std.any()
    moved, _ = dmp.predict(tau, [Condition(0.0, (0.0, 0.2)), Condition(1.0, (1.0, 0.2))])
    np.testing.assert_allclose(moved[[0, -1], 1], [0.2, 0.2], atol=0.02)
    assert moved[50, 1] > 0.6  # the bump is kept on top of the new start/goal


def test_dmp_refuses_what_it_cannot_condition_on():
    tau = np.linspace(0, 1, 50)
    dmp = DMPBaseline().fit([np.stack([tau, tau], 1)])
    assert DMPBaseline.applies([Condition(0.0, (0.0, 0.0)), Condition(1.0, (1.0, 1.0))])
    assert not DMPBaseline.applies([Condition(0.5, (0.5, 0.5))])
    with pytest.raises(ValueError, match="start .phase 0. and goal"):
        dmp.predict(tau, [Condition(0.5, (0.5, 0.5))])
    with pytest.raises(ValueError, match="start .phase 0. and goal"):
        dmp.predict(tau, [Condition(1.0, (np.nan, 0.5), dims=(1,))])
    with pytest.raises(RuntimeError, match="not fitted"):
        DMPBaseline().predict(tau, [Condition(0.0, (0.0, 0.0))])


def test_promp_conditioned_on_task_params_follows_an_unseen_gamma():
    # the demo's amplitude is a linear function of γ[0]; γ[1] is noise the regression must not follow much
    tau = np.linspace(0, 1, 100)
    rng = np.random.default_rng(0)
    gam = np.stack([np.linspace(0.2, 0.6, 8), rng.normal(size=8)], 1)
    demos = [np.stack([tau, g[0] * np.sin(np.pi * tau)], 1) for g in gam]
    promp = ProMPBaseline(n_weights_per_dim=15, context_ridge=1e-3).fit(demos, task_params=gam)
    mean, std = promp.predict(tau, [], task_params=[0.45, 0.0])
    np.testing.assert_allclose(mean[:, 1], 0.45 * np.sin(np.pi * tau), atol=0.02)
    assert std[50, 1] < 0.02  # the amplitude is explained by γ: little spread is left
    plain, plain_std = ProMPBaseline(n_weights_per_dim=15).fit(demos).predict(tau, [])
    assert plain_std[50, 1] > 0.1 and abs(plain[50, 1] - 0.4) < 0.02  # without γ: the average, wide
    # γ and SM conditions together: a via point far from the γ-conditioned mean (0.45) pulls it most of the way
    via, _ = promp.predict([0.5], [Condition(0.5, (0.5, 0.3))], task_params=[0.45, 0.0])
    assert abs(via[0, 1] - 0.3) < 0.02


def test_promp_task_params_bad_inputs():
    tau = np.linspace(0, 1, 50)
    demos = [np.stack([tau, a * tau], 1) for a in (0.1, 0.2, 0.3)]
    with pytest.raises(ValueError, match="one row per demo"):
        ProMPBaseline().fit(demos, task_params=np.zeros((2, 1)))
    with pytest.raises(ValueError, match="NaN"):
        ProMPBaseline().fit(demos, task_params=[[0.0], [np.nan], [1.0]])
    with pytest.raises(ValueError, match="context_ridge"):
        ProMPBaseline(context_ridge=0.0)
    ctx = ProMPBaseline().fit(demos, task_params=[[0.0], [1.0], [2.0]])
    with pytest.raises(ValueError, match="fitted with task_params"):
        ctx.predict([0.5], [])
    with pytest.raises(ValueError, match="1 finite values"):
        ctx.predict([0.5], [], task_params=[0.0, 1.0])
    with pytest.raises(ValueError, match="fitted without task_params"):
        ProMPBaseline().fit(demos).predict([0.5], [], task_params=[0.0])
