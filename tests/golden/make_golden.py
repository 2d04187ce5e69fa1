"""Record the golden checkpoints of tests/test_golden.py (run once, on the code whose behaviour they pin).

For each committed CNMP training config (configs/cnmp_*.json, whose dataset is committed) this builds the
policy on its dataset, takes a few optimizer steps (so the weights are not an initialization), saves the
checkpoint (config.json + model.safetensors + processors, and the initial weights as init.safetensors) under
tests/golden/<config>/ and records the training losses and the
actions of `select_action` and `predict_action_chunk` on a fixed observation sequence (the dataset's first
episode) in actions.npz. The test reloads each checkpoint with the current code and requires the same actions
(up to float rounding: see tests/test_golden.py).

    python tests/golden/make_golden.py            # all configs
    python tests/golden/make_golden.py cnmp_so101_cam --root /tmp/so101_cam_small
                                                  # one config, on a small recording of its dataset's kind (its
                                                  # dataset is not committed; the test then skips the replay of
                                                  # training, whose episode count differs from the config's dataset)
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file

from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.policies.factory import make_policy, make_pre_post_processors

import lerobot_policy_cnmp  # noqa: F401  (registers --policy.type=cnmp)

REPO = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
STEPS = 5  # optimizer steps before saving
FRAMES = 12  # observation sequence length


def observations(ds: LeRobotDataset, keys: list[str]) -> list[dict[str, torch.Tensor]]:
    out = []
    for i in range(FRAMES):
        item = ds[i * 3]
        out.append({k: item[k][None].float() for k in keys})
    return out


def train_steps(policy, n_episodes: int) -> list[float]:
    """STEPS Adam steps on batches of 4 episodes with a fixed generator, on one torch thread (a reduction's
    float order depends on the thread count); the losses."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _train_steps(policy, n_episodes)
    finally:
        torch.set_num_threads(threads)


def _train_steps(policy, n_episodes: int) -> list[float]:
    opt = torch.optim.Adam(policy.parameters(), lr=1e-3)
    g = torch.Generator().manual_seed(0)
    policy.train()
    losses = []
    for _ in range(STEPS):
        batch = {"episode_index": torch.arange(4) % n_episodes}
        loss, _ = policy.forward(batch, generator=g)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return losses


def record(name: str, root: Path | None = None) -> None:
    raw = json.loads((REPO / "configs" / f"{name}.json").read_text())
    root = root or REPO / raw["dataset"]["root"]
    if not (root / "meta" / "info.json").is_file():
        print(f"skip {name}: no dataset at {root}")
        return
    pol = dict(raw["policy"])
    pol.pop("type")
    pol.update(device="cpu", push_to_hub=False)
    cfg = PreTrainedConfig.get_choice_class("cnmp")(**pol)
    meta = LeRobotDatasetMetadata(raw["dataset"]["repo_id"], root=root)
    torch.manual_seed(0)
    policy = make_policy(cfg, ds_meta=meta)
    ds = LeRobotDataset(raw["dataset"]["repo_id"], root=root)
    init = {k: v.detach().clone().contiguous() for k, v in policy.state_dict().items()}
    losses = train_steps(policy, meta.total_episodes)
    policy.eval()
    out = HERE / name
    shutil.rmtree(out, ignore_errors=True)
    policy.save_pretrained(out)
    save_file(init, str(out / "init.safetensors"))
    pre, post = make_pre_post_processors(policy.config, dataset_stats=meta.stats)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    keys = sorted(policy.config.input_features)
    obs = observations(ds, keys)
    torch.manual_seed(1)
    policy.reset()
    steps = np.stack([policy.select_action(dict(o)).numpy() for o in obs])
    torch.manual_seed(2)
    policy.reset()
    chunk = policy.predict_action_chunk(dict(obs[0])).numpy()
    np.savez_compressed(out / "actions.npz", select_action=steps, chunk=chunk, losses=np.asarray(losses),
             train_episodes=np.asarray(meta.total_episodes),
             **{f"obs.{k}": np.stack([o[k].numpy() for o in obs]) for k in keys})
    print(f"{name}: {steps.shape} actions, chunk {chunk.shape}, input {keys}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="Record the golden checkpoints of tests/test_golden.py.")
    parser.add_argument("configs", nargs="*", help="config names (configs/<name>.json); default: every cnmp_* config")
    parser.add_argument("--root", type=Path, help="record one config on this dataset instead of its own")
    args = parser.parse_args()
    if args.root is not None and len(args.configs) != 1:
        parser.error("--root records one config: name exactly one")
    for n in args.configs or sorted(p.stem for p in (REPO / "configs").glob("cnmp_*.json")):
        record(n, args.root)
