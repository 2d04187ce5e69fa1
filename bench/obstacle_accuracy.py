"""Multimodal accuracy on the 2D obstacle task (paper Sec. IV-A, Fig. 4): CNMP vs ProMP vs DMP, same demos.

    python -m bench.obstacle_accuracy [--checkpoint CKPT] [--random 100] [--start_goal 50]

Condition sets: the paper's three, ``--random`` random ones of the sim (via / early / end / via+end /
via-y, both modes) and ``--start_goal`` start + goal pairs of random tasks (both modes). Each method is
conditioned on the condition points only and its predicted mean trajectory is checked: collision-free
(agent disc clear of the obstacle all along) and the error at the conditioned points (on the constrained
dims). Off-demo distance: the largest distance, along the trajectory, from the predicted mean to the
nearest demonstration (a mean between the modes scores high even when it misses the obstacle).
ProMP and DMP are ``movement_primitives``' (31 RBFs per dim, as in the paper), fitted on the dataset the
CNMP was trained on; a DMP only takes a start and a goal, so it runs on the start + goal sets only.
``obstacle_collision_free_<method>`` is over every set the method can take. Also draws Fig. 4's rows.
A missing checkpoint is an error; with ``--train`` the config's CNMP is fitted with the in-memory API first
(~1 min). The JSON's ``checkpoint`` names the checkpoint (path, step, training command).
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from bench.common import CHECKPOINT, DATASET, REPO, add_checkpoint_args, checkpoint_from_args, provenance


def evaluate(predict, condition_sets, phases, demos):
    """Collision-free rate (%), mean error at the conditions, mean off-demo distance, per-set flags."""
    from lerobot_cnmp.sims.obstacle2d.model import AGENT_RADIUS, OBSTACLE_CENTER, OBSTACLE_RADIUS

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
    add_checkpoint_args(p, CHECKPOINT, "a CNMP checkpoint trained on --dataset")
    p.add_argument("--dataset", default=str(DATASET))
    p.add_argument("--random", type=int, default=100)
    p.add_argument("--start_goal", type=int, default=50)
    p.add_argument("--seed", type=int, default=300000)
    p.add_argument("--plot", default=str(REPO / "outputs/fig4_cnmp_vs_promp.png"))
    args = p.parse_args()

    from lerobot_cnmp.api import CNMPModel
    from lerobot_cnmp.promp.baselines import DMPBaseline, ProMPBaseline
    from lerobot_cnmp.execution.conditions import Condition
    from lerobot_cnmp.data.demos import load_demos
    from lerobot_cnmp.sims.obstacle2d.model import OBSTACLE_CENTER, OBSTACLE_RADIUS
    from lerobot_cnmp.sims.obstacle2d.task import PAPER_CONDITIONS, Obstacle2DTask, sample_episode
    from lerobot_cnmp.plot import mode_colors, plot_conditioned_xy

    demos = load_demos(args.dataset)["demos"]
    ckpt = checkpoint_from_args(args, "cnmp_obstacle2d")
    cnmp = CNMPModel.load(ckpt)
    methods = {"CNMP": cnmp.predict, "ProMP": ProMPBaseline().fit(demos).predict, "DMP": DMPBaseline().fit(demos).predict}
    rng = np.random.default_rng(args.seed)
    random_sets = [sample_episode(rng, "random")[1] for _ in range(args.random)]
    start_goal_sets = []
    for _ in range(args.start_goal):
        task = Obstacle2DTask.sample(rng)
        start_goal_sets.append([Condition(0.0, tuple(map(float, task.start))), Condition(1.0, tuple(map(float, task.goal)))])
    families = {"paper": ("paper (3)", list(PAPER_CONDITIONS.values())),
                "random": (f"random ({args.random})", random_sets),
                "startgoal": (f"start+goal ({args.start_goal})", start_goal_sets)}
    phases = np.linspace(0, 1, 200)
    res: dict = {"checkpoint": provenance(ckpt)}
    demo_grid = np.stack([np.stack([np.interp(phases, np.linspace(0, 1, len(d)), d[:, k]) for k in range(d.shape[1])], 1)
                          for d in demos])
    print(f"{'method':<8}{'condition sets':<18}{'collision-free %':>18}{'error at conditions':>22}{'off-demo dist':>15}")
    for name, predict in methods.items():
        key = name.lower()
        usable = []
        for tag, (label, sets) in families.items():
            if name == "DMP" and not all(DMPBaseline.applies(c) for c in sets):
                print(f"{name:<8}{label:<18}{'(cannot condition on these)':>55}")
                continue
            usable += sets
            free, err, off, per = evaluate(predict, sets, phases, demo_grid)
            res[f"obstacle_{tag}_collision_free_{key}"] = round(free, 1)
            res[f"obstacle_{tag}_condition_error_{key}"] = round(err, 4)
            res[f"obstacle_{tag}_off_demo_distance_{key}"] = round(off, 4)
            if tag == "paper":
                res[f"obstacle_paper_per_condition_{key}"] = dict(zip(PAPER_CONDITIONS, per, strict=True))
            print(f"{name:<8}{label:<18}{free:>18.1f}{err:>22.4f}{off:>15.3f}")
        res[f"obstacle_collision_free_{key}"] = round(evaluate(predict, usable, phases, demo_grid)[0], 1)
    methods.pop("DMP")  # Fig. 4's conditions are not start + goal
    plot = plot_conditioned_xy(demos, PAPER_CONDITIONS, methods, args.plot, demo_colors=mode_colors(demos),
                               obstacle=(tuple(OBSTACLE_CENTER), OBSTACLE_RADIUS))
    print(f"plot: {plot}")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
