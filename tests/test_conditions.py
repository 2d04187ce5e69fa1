"""One condition type and one validator: user dicts, Condition objects, environment_state slots and the Python
API all pass through lerobot_cnmp.execution.conditions.check_points, with the same rules and messages."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE

from lerobot_cnmp.api import load_pretrained
from lerobot_cnmp.execution.conditions import (Condition, check_conditions, check_points, conditions_from_vector,
                                               encode_conditions)

GOLDEN = Path(__file__).resolve().parent / "golden"


@pytest.mark.parametrize("cond, match", [
    (Condition(1.5, (0.0, 0.0)), r"condition 0: phase 1.5 is outside \[0, 1\]"),
    (Condition(float("nan"), (0.0, 0.0)), "phase is NaN"),
    (Condition(0.5, (float("inf"), 0.0)), "NaN or infinite values in a constrained dim"),
    (Condition(0.5, (0.0,)), "the SM has 2 dims"),
    (Condition(0.5, (0.0, 0.0), dims=(2,)), "valid SM dims are 0..1"),
])
def test_one_validator_for_condition_objects_and_slots(cond, match):
    with pytest.raises(ValueError, match=match):
        check_conditions([cond], 2)
    with pytest.raises(ValueError, match=match):
        encode_conditions([cond], 2, 4)


def test_unconstrained_dims_may_be_nan_and_capacity_is_checked():
    ok = Condition(0.5, (float("nan"), 0.3), dims=(1,))
    assert check_conditions([ok], 2) == [ok]
    assert conditions_from_vector(encode_conditions([ok], 2, 4), 2)[0].dims == (1,)
    with pytest.raises(ValueError, match="at most 1"):
        check_conditions([ok, ok], 2, capacity=1)
    phase = np.array([[0.5, 2.0]])  # env 0, slot 1 is present with a phase outside [0, 1]
    with pytest.raises(ValueError, match=r"slot 1 \(env 0\): phase 2"):
        check_points(phase, np.zeros((1, 2, 2)), np.ones((1, 2, 2)), np.ones((1, 2)), source="slot")
    check_points(phase, np.zeros((1, 2, 2)), np.ones((1, 2, 2)), np.array([[1.0, 0.0]]))  # absent: not checked


def test_the_executor_takes_condition_objects_and_checks_env_slots():
    policy, _, _ = load_pretrained(GOLDEN / "cnmp_obstacle2d", device="cpu")
    policy.eval()
    policy.set_conditions([Condition(1.0, (0.9, 0.1))])
    assert policy.executor.conditions == [Condition(1.0, (0.9, 0.1))]
    with pytest.raises(ValueError, match="outside"):
        policy.set_conditions([Condition(1.2, (0.9, 0.1))])
    policy.set_conditions(None)
    slots = torch.from_numpy(encode_conditions([Condition(1.0, (0.9, 0.1))], 2, 4))[None]
    policy.reset()
    policy.select_action({OBS_STATE: torch.zeros(1, 2), OBS_ENV_STATE: slots})
    bad = slots.clone()
    bad[0, 1] = 1.5  # slot 0's phase
    policy.reset()
    with pytest.raises(ValueError, match=r"environment_state condition 0 \(env 0\): phase 1.5 is outside"):
        policy.select_action({OBS_STATE: torch.zeros(1, 2), OBS_ENV_STATE: bad})
