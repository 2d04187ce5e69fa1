"""What does an image CNMP's encoder know about the scene? A linear probe of the dataset's ground-truth γ.

    python -m bench.camera_probe --checkpoint CKPT --dataset datasets/cnmp_metaworld_push_cam
    python -m bench.camera_probe --checkpoint CKPT --dataset datasets/cnmp_metaworld_push_cam --heldout_task push-v3

Embeds each episode's first frame with the checkpoint's conv encoders (as training and execution do) and fits a
ridge regression from the embeddings to ``ground_truth.task_params`` (the object and goal positions the policy
never reads), leave-one-episode-out. Prints R² per γ entry: near 1, the embedding locates that entry; <= 0, it
carries nothing linear about it (an entry constant over the dataset, such as the table height, has no R²).
With ``--heldout_task``, also the R² on scenes the encoder never saw: the ridge fitted on all the dataset's
episodes predicts γ from the first camera frames of ``--heldout`` fresh ``cnmp_metaworld`` resets (the
evaluation's seeds, 100000 on), rendered live as in execution. Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch


def ridge_fit(x: np.ndarray, y: np.ndarray, ridge: float) -> np.ndarray:
    """Weights of the ridge regression y ~ [x, 1]."""
    xb = np.c_[x, np.ones(len(x))]
    return np.linalg.solve(xb.T @ xb + ridge * np.eye(xb.shape[1]), xb.T @ y)


def r2_per_column(err: np.ndarray, y: np.ndarray) -> list[float | None]:
    """1 - mean squared error / variance of y, per column (None for a column constant in y)."""
    return [None if v < 1e-10 else round(float(1 - (e ** 2).mean() / v), 3) for e, v in zip(err.T, y.var(0))]


def loo_r2(x: np.ndarray, y: np.ndarray, ridge: float = 1e-2) -> list[float | None]:
    """Leave-one-out R² of a ridge regression y ~ [x, 1], per column of y (None for a constant column)."""
    err = np.empty_like(y)
    for i in range(len(x)):
        keep = np.arange(len(x)) != i
        err[i] = np.r_[x[i], 1.0] @ ridge_fit(x[keep], y[keep], ridge) - y[i]
    return r2_per_column(err, y)


def heldout_r2(x: np.ndarray, y: np.ndarray, x_new: np.ndarray, y_new: np.ndarray, ridge: float = 1e-2
               ) -> list[float | None]:
    """R² on (x_new, y_new) of a ridge regression y ~ [x, 1] fitted on all of (x, y), per column of y (None for
    a column constant in y_new)."""
    err = np.c_[x_new, np.ones(len(x_new))] @ ridge_fit(x, y, ridge) - y_new
    return r2_per_column(err, y_new)


def embedding(policy, frames: dict[str, torch.Tensor]) -> np.ndarray:
    """The episode-level image embedding (every image feature's, concatenated) of one frame per feature [1, C, H, W]."""
    from lerobot_cnmp.policy.inputs import embed

    with torch.no_grad():
        return torch.cat([embed(policy.image_encoders, k, frames[k]) for k in policy.config.image_keys], -1)[0].numpy()


def heldout_scenes(policy, task: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Embeddings and γ of the first frames of ``n`` fresh resets of ``cnmp_metaworld`` ``task`` (seeds 100000
    on), rendered at the checkpoint's camera size."""
    from lerobot_cnmp.sims.metaworld.env import MetaWorldEnv

    keys = policy.config.image_keys
    cams = [k.removeprefix("observation.images.") for k in keys]
    size = int(policy.config.input_features[keys[0]].shape[-1])
    env = MetaWorldEnv(task=task, max_episode_steps=10, cameras=cams, camera_size=size)
    emb, gamma = [], []
    for i in range(n):
        obs, info = env.reset(seed=100000 + i)
        emb.append(embedding(policy, {k: torch.from_numpy(obs["pixels"][c]).permute(2, 0, 1)[None].float() / 255.0
                                      for c, k in zip(cams, keys)}))
        gamma.append(np.asarray(info["task_params"], dtype=np.float64))
    env.close()
    return np.array(emb), np.array(gamma)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--dataset", required=True, help="a camera dataset with ground_truth.task_params")
    p.add_argument("--heldout_task", help="a MetaWorld task (e.g. push-v3): also probe fresh scenes of it")
    p.add_argument("--heldout", type=int, default=40, help="number of fresh scenes (seeds 100000 on)")
    args = p.parse_args(argv)

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_cnmp.api import load_pretrained
    from lerobot_cnmp.sims.cameras import GROUND_TRUTH_TASK_PARAMS

    policy, _, _ = load_pretrained(args.checkpoint, device="cpu")
    policy.eval()
    ds = LeRobotDataset("local/probe", root=args.dataset)
    if GROUND_TRUTH_TASK_PARAMS not in ds.meta.features:
        raise SystemExit(f"error: {args.dataset} has no {GROUND_TRUTH_TASK_PARAMS} (record it with --cameras)")
    emb, gamma = [], []
    for start in np.asarray(ds.meta.episodes["dataset_from_index"]):
        item = ds[int(start)]
        emb.append(embedding(policy, {k: item[k][None] for k in policy.config.image_keys}))
        gamma.append(item[GROUND_TRUTH_TASK_PARAMS].numpy())
    names = ds.meta.features[GROUND_TRUTH_TASK_PARAMS]["names"]
    r2 = loo_r2(np.array(emb), np.array(gamma))
    res = {"checkpoint": args.checkpoint, "dataset": args.dataset, "episodes": len(emb),
           "loo_r2": dict(zip(names, r2))}
    if args.heldout_task:
        x, y = heldout_scenes(policy, args.heldout_task, args.heldout)
        res.update(heldout_task=args.heldout_task, heldout_seeds=[100000, 100000 + args.heldout - 1],
                   heldout_r2=dict(zip(names, heldout_r2(np.array(emb), np.array(gamma), x, y))))
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
