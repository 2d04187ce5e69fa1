"""Learning end to end: a tiny CNMP trained from scratch on part of the obstacle dataset must succeed in the sim.

A regression anywhere in learning (sampler, loss, normalization, optimizer, checkpoint round trip, execution)
shows up here as a success rate below the bar, judged by the sim's own rule (``info["is_success"]``: goal
reached, conditions passed, no contact) over episodes run with LeRobot's ``rollout`` as ``lerobot-eval`` runs
them. The same pipeline with one training step is checked to fail, so the bar is not met by an untrained net.
"""

from pathlib import Path

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]

DATASET = REPO / "datasets" / "cnmp_obstacle2d"
N_DEMOS = 16  # of the dataset's 64 (balanced modes: even episodes over, odd under)
STEPS = 2000
EPISODES = 30
BAR = 70.0  # % of episodes; the trained net reaches ~90 %, the untrained one 0 %


def success_rate(ckpt: Path, episodes: int, seed: int) -> float:
    from bench.common import make_sim
    from lerobot.scripts.lerobot_eval import rollout

    from lerobot_cnmp.api import load_pretrained
    from lerobot_cnmp.sims.obstacle2d.config import CNMPObstacle2DEnv

    policy, pre, post = load_pretrained(ckpt)
    env, env_pre, env_post = make_sim(CNMPObstacle2DEnv(conditions="random", render_mode=None), policy, 10)
    try:
        wins = []
        for start in range(0, episodes, 10):
            data = rollout(env, policy, env_pre, env_post, pre, post, seeds=list(range(seed + start, seed + start + 10)))
            wins += data["success"].any(dim=1).tolist()
    finally:
        env.close()
    return 100.0 * float(np.mean(wins[:episodes]))


def fit_and_save(steps: int, out: Path) -> Path:
    from bench.common import api_model, config

    from lerobot_cnmp.data.demos import load_demos

    torch.set_num_threads(1)
    demos = load_demos(DATASET)["demos"][:N_DEMOS]
    model = api_model(config()).fit(demos, steps=steps, batch_size=8, seed=0, progress=False)
    return model.save(out)


@pytest.mark.skipif(not (DATASET / "meta" / "info.json").is_file(), reason="datasets/cnmp_obstacle2d not built")
def test_tiny_cnmp_learns_the_obstacle_task(tmp_path):
    untrained = success_rate(fit_and_save(1, tmp_path / "untrained"), 10, seed=500000)
    assert untrained <= 10.0, f"an untrained CNMP succeeds in {untrained:.0f} % of episodes: the bar would not test learning"
    trained = success_rate(fit_and_save(STEPS, tmp_path / "trained"), EPISODES, seed=500000)
    assert trained >= BAR, (f"a CNMP trained {STEPS} steps on {N_DEMOS} demos succeeds in {trained:.0f} % of "
                            f"{EPISODES} episodes (bar {BAR:.0f} %): learning regressed")
