"""Multimodal accuracy on the 2D obstacle task (paper Sec. IV-A, Fig. 4): CNMP vs ProMP on the same demos.

    python bench/obstacle_accuracy.py [--checkpoint CKPT] [--random 100]

For the paper's three conditions and ``--random`` random condition sets of the sim (both modes), each
method is conditioned on the condition points only and its predicted mean trajectory is checked:
collision-free (agent disc clear of the obstacle all along) and the error at the conditioned points (on
the constrained dims). ProMP is ``movement_primitives``' (31 RBFs per dim, as in the paper), fitted on the
same dataset the CNMP checkpoint was trained on. Off-demo distance: the largest distance, along the
trajectory, from the predicted mean to the nearest demonstration (a mean between the modes scores high
even when it misses the obstacle). Also draws both rows of Fig. 4.
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def evaluate(predict, condition_sets, phases, demos):
    """Collision-free rate (%), mean error at the conditions, mean off-demo distance, per-set flags."""
    from lerobot_cnmp.envs.obstacle2d import AGENT_RADIUS, OBSTACLE_CENTER, OBSTACLE_RADIUS

    free, errors, off = [], [], []
    for conds in condition_sets:
        mean, _ = predict(phases, conds)
        clearance = np.linalg.norm(mean - OBSTACLE_CENTER, axis=1) - OBSTACLE_RADIUS - AGENT_RADIUS
        free.append(bool(clearance.min() > 0))
        at, _ = predict(np.array([c.phase for c in conds]), conds)
        errors.append(np.mean([np.linalg.norm((at[k] - np.asarray(c.values)) * c.mask()) for k, c in enumerate(conds)]))
        # Mode fidelity: at each phase, the distance to the nearest demonstration; its largest value.
        off.append(float(np.linalg.norm(mean[None] - demos, axis=-1).min(axis=0).max()))
    return 100.0 * np.mean(free), float(np.mean(errors)), float(np.mean(off)), free


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default=str(REPO / "outputs/main/train/checkpoints/last/pretrained_model"))
    p.add_argument("--dataset", default=str(REPO / "datasets/cnmp_obstacle2d"))
    p.add_argument("--random", type=int, default=100)
    p.add_argument("--seed", type=int, default=300000)
    p.add_argument("--plot", default=str(REPO / "outputs/fig4_cnmp_vs_promp.png"))
    args = p.parse_args()

    from lerobot_cnmp.api import CNMPModel
    from lerobot_cnmp.baselines import ProMPBaseline
    from lerobot_cnmp.data import load_demos
    from lerobot_cnmp.envs.obstacle2d import OBSTACLE_CENTER, OBSTACLE_RADIUS, PAPER_CONDITIONS, sample_episode
    from lerobot_cnmp.plot import mode_colors, plot_conditioned_xy

    demos = load_demos(args.dataset)["demos"]
    methods = {"CNMP": CNMPModel.load(args.checkpoint).predict, "ProMP": ProMPBaseline().fit(demos).predict}
    rng = np.random.default_rng(args.seed)
    random_sets = [sample_episode(rng, "random")[1] for _ in range(args.random)]
    phases = np.linspace(0, 1, 200)
    res: dict = {}
    demo_grid = np.stack([np.stack([np.interp(phases, np.linspace(0, 1, len(d)), d[:, k]) for k in range(d.shape[1])], 1)
                          for d in demos])
    print(f"{'method':<8}{'condition set':<16}{'collision-free %':>18}{'error at conditions':>22}{'off-demo dist':>15}")
    for name, predict in methods.items():
        key = name.lower()
        for label, sets in (("paper (3)", list(PAPER_CONDITIONS.values())), (f"random ({args.random})", random_sets)):
            free, err, off, per = evaluate(predict, sets, phases, demo_grid)
            tag = "paper" if label.startswith("paper") else "random"
            res[f"obstacle_{tag}_collision_free_{key}"] = round(free, 1)
            res[f"obstacle_{tag}_condition_error_{key}"] = round(err, 4)
            res[f"obstacle_{tag}_off_demo_distance_{key}"] = round(off, 4)
            if tag == "paper":
                res[f"obstacle_paper_per_condition_{key}"] = dict(zip(PAPER_CONDITIONS, per, strict=True))
            print(f"{name:<8}{label:<16}{free:>18.1f}{err:>22.4f}{off:>15.3f}")
        all_sets = list(PAPER_CONDITIONS.values()) + random_sets
        res[f"obstacle_collision_free_{key}"] = round(evaluate(predict, all_sets, phases, demo_grid)[0], 1)
    plot = plot_conditioned_xy(demos, PAPER_CONDITIONS, methods, args.plot, demo_colors=mode_colors(demos),
                               obstacle=(tuple(OBSTACLE_CENTER), OBSTACLE_RADIUS))
    print(f"plot: {plot}")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
