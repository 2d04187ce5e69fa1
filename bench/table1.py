"""Table I of the paper on the pick-and-place sim: joint errors for new task parameters γ, and execution.

    python -m bench.table1 [--checkpoint CKPT] [--random 30]

For the paper's three interpolation and three extrapolation γ = (object cm, obstacle cm), the CNMP is
conditioned on γ and the start state (the home posture) and predicts the 200-step joint trajectory; each
joint's error is the mean over the trajectory of |prediction - ground truth| in degrees, the ground truth
being the scripted expert's plan for that γ (``reference_trajectory``). Each γ is also executed in the sim
by the policy (online feedback, PD, phase stopping; LeRobot's ``rollout``, as ``lerobot-eval`` runs it),
and ``--random`` episodes with γ drawn uniformly inside the training range give the interpolation success
rate. Extrapolated γ (outside object 2-6 cm, obstacle 2-8 cm) are flagged in the table. Also draws a figure
like the paper's Fig. 8 (demos gray, ground truth dashed, prediction ± 2σ) for three joints.
A missing checkpoint is an error; with ``--train`` the config's CNMP is fitted with the in-memory API first (~1 min).
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bench.common import REPO, add_checkpoint_args, checkpoint_from_args, make_sim, provenance

CONFIG = REPO / "configs" / "cnmp_pickplace.json"
CHECKPOINT = REPO / "outputs" / "pickplace" / "train" / "checkpoints" / "last" / "pretrained_model"
PAPER_TABLE_I_MAX = {(3.0, 3.0): 0.271, (3.0, 6.0): 0.167, (4.0, 7.0): 0.280, (7.0, 9.0): 3.687,
                     (8.0, 10.0): 8.879, (9.0, 11.0): 17.978}
"""The paper's worst joint error (deg) per γ (Table I), for reference."""


def key(gamma) -> str:
    return f"{gamma[0]:g}_{gamma[1]:g}"


def execute(policy, pre, post, gammas: list | None, episodes: int, seed: int) -> list[bool]:
    """Success per episode: one per γ of ``gammas``, or ``episodes`` with γ drawn by the env."""
    from lerobot.scripts.lerobot_eval import rollout

    from lerobot_cnmp.sims.pickplace.config import CNMPPickPlaceEnv

    runs = [(g, 1) for g in gammas] if gammas else [(None, episodes)]
    out = []
    for gamma, n in runs:
        batch = min(n, 10)
        env, env_pre, env_post = make_sim(CNMPPickPlaceEnv(task_params=gamma, render_mode=None), policy, batch)
        for start in range(0, n, batch):
            data = rollout(env, policy, env_pre, env_post, pre, post, seeds=list(range(seed + start, seed + start + batch)))
            out += [bool(s.any()) for s in data["success"]][: n - start]
        env.close()
    return out


def plot_fig8(model, demos, gammas, phases, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lerobot_cnmp.execution.conditions import Condition
    from lerobot_cnmp.sims.pickplace.kinematics import reference_trajectory
    from lerobot_cnmp.sims.pickplace.model import JOINT_NAMES

    joints = (1, 2, 3)  # shoulder, elbow, wrist 1: the joints the arc moves most
    fig, axes = plt.subplots(len(joints), len(gammas), figsize=(4.2 * len(gammas), 2.6 * len(joints)), sharex=True)
    start = Condition(0.0, tuple(float(v) for v in demos[0][0]))
    for c, gamma in enumerate(gammas):
        mean, std = model.predict(phases, [start], task_params=gamma)
        truth = reference_trajectory(gamma, len(phases))
        for r, j in enumerate(joints):
            ax = axes[r, c]
            for d in demos:
                ax.plot(np.linspace(0, 1, len(d)), np.degrees(d[:, j]), color="0.7", lw=0.8)
            ax.plot(phases, np.degrees(truth[:, j]), "b--", lw=1.5, label="ground truth")
            ax.plot(phases, np.degrees(mean[:, j]), "r-", lw=1.2, label="prediction")
            ax.fill_between(phases, np.degrees(mean[:, j] - 2 * std[:, j]), np.degrees(mean[:, j] + 2 * std[:, j]),
                            color="r", alpha=0.2)
            if c == 0:
                ax.set_ylabel(f"{JOINT_NAMES[j]} (deg)")
            if r == 0:
                ax.set_title(f"γ = ({gamma[0]:g}, {gamma[1]:g}) cm")
        axes[-1, c].set_xlabel("phase")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Pick and place: demos (gray), ground truth (dashed), CNMP prediction ± 2σ")
    fig.tight_layout()
    from lerobot_cnmp.plot import save_figure

    return save_figure(fig, path, dpi=110)


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_checkpoint_args(p, CHECKPOINT, "a CNMP checkpoint trained on cnmp_pickplace")
    p.add_argument("--random", type=int, default=30, help="executed episodes with random interpolation γ")
    p.add_argument("--seed", type=int, default=700000)
    p.add_argument("--plot", default=str(REPO / "outputs" / "fig8_pickplace.png"))
    args = p.parse_args()

    from lerobot_cnmp.api import CNMPModel, load_pretrained
    from lerobot_cnmp.execution.conditions import Condition
    from lerobot_cnmp.data.demos import load_demos
    from lerobot_cnmp.sims.pickplace.kinematics import reference_trajectory
    from lerobot_cnmp.sims.pickplace.model import JOINT_NAMES
    from lerobot_cnmp.sims.pickplace.planner import PAPER_EXTRAPOLATION, PAPER_INTERPOLATION, is_extrapolation

    demos = load_demos(REPO / "datasets" / "cnmp_pickplace")["demos"]
    ckpt = checkpoint_from_args(args, "cnmp_pickplace", config_path=CONFIG)
    model = CNMPModel.load(ckpt)
    policy, pre, post = load_pretrained(ckpt)
    phases = np.linspace(0.0, 1.0, 200)
    start = Condition(0.0, tuple(float(v) for v in demos[0][0]))
    gammas = [*PAPER_INTERPOLATION, *PAPER_EXTRAPOLATION]
    errors = {}
    for gamma in gammas:
        mean, _ = model.predict(phases, [start], task_params=gamma)
        errors[gamma] = np.degrees(np.abs(mean[:, :6] - reference_trajectory(gamma)[:, :6]).mean(axis=0))
    success = dict(zip(gammas, execute(policy, pre, post, gammas, 1, args.seed), strict=True))
    random_success = execute(policy, pre, post, None, args.random, args.seed + 1000) if args.random else []

    print("mean absolute joint error (deg) between prediction and ground truth; * = outside the training range")
    print(f"{'γ (cm)':<12}" + "".join(f"{n:>9}" for n in JOINT_NAMES) + f"{'max':>8}{'paper max':>11}{'executed':>10}")
    for gamma in gammas:
        tag = f"({gamma[0]:g}, {gamma[1]:g}){'*' if is_extrapolation(gamma) else ''}"
        e = errors[gamma]
        print(f"{tag:<12}" + "".join(f"{v:>9.3f}" for v in e) + f"{e.max():>8.3f}{PAPER_TABLE_I_MAX[gamma]:>11.3f}"
              f"{'success' if success[gamma] else 'FAIL':>10}")
    interp = [g for g in gammas if not is_extrapolation(g)]
    res = {
        "checkpoint": provenance(ckpt),
        "interp_max_err_deg": round(float(max(errors[g].max() for g in interp)), 4),
        "interp_mean_err_deg": round(float(np.mean([errors[g].mean() for g in interp])), 4),
        **{f"extrap_{key(g)}_max_err_deg": round(float(errors[g].max()), 4) for g in PAPER_EXTRAPOLATION},
        "interp_success_pct": round(100.0 * np.mean(random_success), 1) if random_success else None,
        "interp_success_episodes": len(random_success),
        "paper_gamma_success": {key(g): success[g] for g in gammas},
        "extrap_7_9_success": success[(7.0, 9.0)],
        "errors_deg": {key(g): [round(float(v), 4) for v in errors[g]] for g in gammas},
        "extrapolated": {key(g): is_extrapolation(g) for g in gammas},
    }
    if random_success:
        print(f"executed with random interpolation γ: {res['interp_success_pct']:.1f} % success "
              f"({sum(random_success)} / {len(random_success)})")
    res["plot"] = str(plot_fig8(model, demos, [(3.0, 3.0), (4.0, 7.0), (7.0, 9.0)], phases, Path(args.plot)))
    print(f"plot: {res['plot']}")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
