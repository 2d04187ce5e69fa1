"""The in-memory demonstrations and the training draw (lerobot_cnmp.data.bank): whole-episode draws, phases from
timestamps, length-proportional episode sampling, one sampler for the API and lerobot-train."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

from lerobot_cnmp.data import sm_spec
from lerobot_cnmp.data.bank import TASK_STD_FLOOR, EpisodeBank, floored_std

REPO = Path(__file__).resolve().parents[1]
DATASET = REPO / "datasets" / "cnmp_obstacle2d"


def test_draws_cover_the_whole_episode_with_data_phases():
    demos = [np.arange(t, dtype=np.float32)[:, None] * np.ones((1, 2), np.float32) for t in (10, 1000)]
    bank = EpisodeBank.from_arrays(demos)
    gen = torch.Generator().manual_seed(0)
    values, phase = bank.draw(torch.tensor([1] * 64), 16, gen)
    assert values.shape == (64, 16, 2) and phase.shape == (64, 16) and bank.task_params_of(torch.tensor([1])) is None
    frames = values[..., 0]
    torch.testing.assert_close(phase, frames / 999)  # phase = frame / (T - 1)
    assert frames.min() < 50 and frames.max() > 950  # every draw spans the whole 1000-frame episode
    short, _ = bank.draw(torch.tensor([0] * 64), 16, gen)
    assert short.max() <= 9 and short.min() >= 0


def test_episodes_are_sampled_in_proportion_to_their_length():
    bank = EpisodeBank.from_arrays([np.zeros((t, 1), np.float32) for t in (100, 300)])
    ep = bank.sample_episodes(20000, torch.Generator().manual_seed(1))
    share = float((ep == 1).float().mean())
    assert abs(share - 0.75) < 0.02


def test_dataset_bank_reads_the_sm_columns_and_phases():
    meta = LeRobotDatasetMetadata("x", root=DATASET)
    spec = sm_spec.resolve(None, None, True, meta.features)
    bank = EpisodeBank.from_dataset(DATASET, spec)
    assert bank.n_episodes == 64 and bank.values.shape == (64 * 200, 2)
    # episode 3's frames in order, at phase k / 199 (timestamps at a constant 50 fps)
    rows = slice(int(bank.starts[3]), int(bank.starts[3]) + 200)
    torch.testing.assert_close(bank.phase[rows], torch.arange(200, dtype=torch.float32) / 199)
    assert bank.median_duration_s() == pytest.approx(199 / 50)
    # the values are the dataset's action column
    from lerobot_cnmp.data.demos import load_demos

    np.testing.assert_array_equal(bank.values[rows].numpy(), load_demos(DATASET)["demos"][3])


def test_std_floor():
    std = floored_std([1.0, 2.0, 1e-9, 0.0])
    assert std[0] == 1.0 and std[2] == pytest.approx(5e-3) and std[3] == pytest.approx(5e-3)  # 1 % of the median
    np.testing.assert_array_equal(floored_std([0.0, 0.0]), [1.0, 1.0])  # never moves: unit scale


def test_task_params_floor_quiets_a_near_constant_dim():
    """γ's floor is 10 % of the median γ std: a dim ~30x quieter than the others (coffee-push-v3's resting heights)
    is not scaled up to unit variance; a dim within 10x of the median is; the SM keeps its 1 % floor."""
    rng = np.random.default_rng(0)
    gamma = np.stack([rng.normal(0, s, 50) for s in (0.07, 0.02, 0.0006, 0.025, 0.012, 0.0006)], 1)
    bank = EpisodeBank.from_arrays([np.zeros((5, 1), np.float32)] * 50, task_params=gamma)
    mean, std = bank.task_stats()
    raw = gamma.std(0)
    med = np.median(raw)
    assert TASK_STD_FLOOR == 0.1
    np.testing.assert_allclose(std[[2, 5]], TASK_STD_FLOOR * med, rtol=1e-5)  # floored: noise scaled to ~0.3
    np.testing.assert_allclose(std[[0, 1, 3, 4]], raw[[0, 1, 3, 4]], rtol=1e-5)  # real dims: unit variance
    assert float(np.abs((gamma[:, 2] - mean[2]) / std[2]).max()) < 1.5
    np.testing.assert_allclose(floored_std(raw)[[2, 5]], raw[[2, 5]], rtol=1e-5)  # the SM's 1 % floor would not
