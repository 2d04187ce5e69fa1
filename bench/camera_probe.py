"""What does an image CNMP's encoder know about the scene? A linear probe of the dataset's ground-truth γ.

    python -m bench.camera_probe --checkpoint CKPT --dataset datasets/cnmp_metaworld_push_cam

Embeds each episode's first frame with the checkpoint's conv encoders (as training and execution do) and fits a
ridge regression from the embeddings to ``ground_truth.task_params`` (the object and goal positions the policy
never reads), leave-one-episode-out. Prints R² per γ entry: near 1, the embedding locates that entry; <= 0, it
carries nothing linear about it (an entry constant over the dataset, such as the table height, has no R²).
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch


def loo_r2(x: np.ndarray, y: np.ndarray, ridge: float = 1e-2) -> list[float | None]:
    """Leave-one-out R² of a ridge regression y ~ [x, 1], per column of y (None for a constant column)."""
    xb = np.c_[x, np.ones(len(x))]
    err = np.empty_like(y)
    for i in range(len(x)):
        keep = np.arange(len(x)) != i
        w = np.linalg.solve(xb[keep].T @ xb[keep] + ridge * np.eye(xb.shape[1]), xb[keep].T @ y[keep])
        err[i] = xb[i] @ w - y[i]
    var = y.var(0)
    return [None if v < 1e-10 else round(float(1 - (e ** 2).mean() / v), 3) for e, v in zip(err.T, var)]


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--dataset", required=True, help="a camera dataset with ground_truth.task_params")
    args = p.parse_args(argv)

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_cnmp.api import load_pretrained
    from lerobot_cnmp.policy.inputs import embed
    from lerobot_cnmp.sims.cameras import GROUND_TRUTH_TASK_PARAMS

    policy, _, _ = load_pretrained(args.checkpoint, device="cpu")
    policy.eval()
    ds = LeRobotDataset("local/probe", root=args.dataset)
    if GROUND_TRUTH_TASK_PARAMS not in ds.meta.features:
        raise SystemExit(f"error: {args.dataset} has no {GROUND_TRUTH_TASK_PARAMS} (record it with --cameras)")
    emb, gamma = [], []
    with torch.no_grad():
        for start in np.asarray(ds.meta.episodes["dataset_from_index"]):
            item = ds[int(start)]
            emb.append(torch.cat([embed(policy.image_encoders, k, item[k][None]) for k in policy.config.image_keys],
                                 -1)[0].numpy())
            gamma.append(item[GROUND_TRUTH_TASK_PARAMS].numpy())
    names = ds.meta.features[GROUND_TRUTH_TASK_PARAMS]["names"]
    r2 = loo_r2(np.array(emb), np.array(gamma))
    res = {"checkpoint": args.checkpoint, "dataset": args.dataset, "episodes": len(emb),
           "loo_r2": dict(zip(names, r2))}
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
