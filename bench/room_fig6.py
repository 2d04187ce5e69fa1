"""Image-conditioned CNMP in unseen rooms, as in the paper's Fig. 6.

    python -m bench.room_fig6 [--checkpoint CKPT] [--rooms 3] [--seed 100000] [--out PNG]

For ``--rooms`` rooms not in the dataset (reset seeds ``seed``, ``seed + 1``, ...; the dataset's rooms use
seeds 0-999) and each condition type of ``cnmp_room`` (columns: start and end, via point and end, via
point only), the trained CNMP sees the room's top-down mask and the episode's conditions and

* predicts the whole trajectory from the first step's context (mean and ± 2σ band, the paper's figure),
* runs closed loop as ``lerobot-eval`` runs it (the config's online feedback and phase stop), whose
  executed path and success are shown.

Each panel also shows the planner's path in that room (dashed, what a demo would be). Needs a trained
checkpoint (``lerobot-train --config_path=configs/cnmp_room.json``). Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bench.common import REPO, policy_batch, predict_sm, provenance

CHECKPOINT = REPO / "outputs" / "room" / "train" / "checkpoints" / "last" / "pretrained_model"
OUT = REPO / "docs" / "fig6_room.png"
TITLES = {"start_end": "(a) start and end", "via_end": "(b) via point and end", "via": "(c) via point"}


def run_episode(policy, pre, post, env, seed: int, n_phases: int = 100) -> dict:
    """One closed-loop episode in ``env`` (a :class:`RoomEnv`) reset with ``seed``: the executed path, the
    final info, and the trajectory predicted from the first step's context (mean, σ: [n_phases, 2])."""
    import torch

    obs, info = env.reset(seed=seed)
    policy.reset()
    path, predicted = [obs["agent_pos"].copy()], None
    for _ in range(env.spec.max_episode_steps if env.spec else 150):
        batch = policy_batch(pre, obs)
        with torch.no_grad():
            action = policy.select_action(batch)
        if predicted is None:  # the plan of the first step: conditions, start, image
            predicted = predict_sm(policy, pre, post, batch, 0.0, np.linspace(0.0, 1.0, n_phases))
        obs, _, terminated, truncated, info = env.step(post(action)[0].numpy())
        path.append(obs["agent_pos"].copy())
        if terminated or truncated:
            break
    return {"path": np.asarray(path), "info": info, "mean": predicted[0], "std": predicted[1]}


def plot(results: dict, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lerobot_cnmp.sims.room.planner import plan_path

    rooms = len(next(iter(results.values())))
    fig, axes = plt.subplots(rooms, len(results), figsize=(3.6 * len(results), 3.6 * rooms), squeeze=False)
    for c, (kind, episodes) in enumerate(results.items()):
        for r, ep in enumerate(episodes):
            ax = axes[r, c]
            ax.imshow(ep["mask"][..., 0], cmap="gray_r", vmin=0, vmax=255 * 2.5, extent=(0, 1, 0, 1),
                      origin="upper", interpolation="nearest")
            planned = plan_path(ep["task"], np.linspace(0, 1, 200))
            ax.plot(planned[:, 0], planned[:, 1], "--", color="tab:green", lw=1, label="planner (demo-like)")
            m, s = ep["mean"], ep["std"]
            for k in range(len(m)):  # ± 2σ as discs along the mean, the paper's shaded tube
                ax.add_patch(plt.Circle(m[k], 2 * float(np.mean(s[k])), color="tab:gray", alpha=0.08, lw=0))
            ax.plot(m[:, 0], m[:, 1], "k-", lw=2, label="CNMP mean (± 2σ)")
            p = ep["path"]
            ax.plot(p[:, 0], p[:, 1], "-", color="tab:blue", lw=1.2, label="executed")
            for cond in ep["conditions"]:
                ax.plot(*cond.values, "o", color="k", ms=8, mfc="yellow", zorder=5)
            info = ep["info"]
            verdict = "success" if info["is_success"] else ("collision" if info["collision"] else "failure")
            ax.set_title(f"{TITLES[kind]}: {verdict}", fontsize=9)
            ax.set_xlim(0, 1)
            ax.set_ylim(0, 1)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
    axes[0, 0].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    from lerobot_cnmp.plot import save_figure

    return save_figure(fig, out, dpi=110)


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default=str(CHECKPOINT))
    p.add_argument("--rooms", type=int, default=3)
    p.add_argument("--seed", type=int, default=100000)
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args()
    if not (Path(args.checkpoint) / "config.json").is_file():
        p.error(f"no checkpoint at {args.checkpoint}: train one with "
                "`lerobot-train --config_path=configs/cnmp_room.json --output_dir=outputs/room/train`")

    import gymnasium as gym

    from lerobot_cnmp.api import load_pretrained
    from lerobot_cnmp.sims.room.config import ROOM_GYM_ID
    from lerobot_cnmp.sims.room.task import CONDITION_CHOICES

    policy, pre, post = load_pretrained(args.checkpoint)
    policy.eval()
    results, summary = {}, {}
    for kind in CONDITION_CHOICES:
        env = gym.make(ROOM_GYM_ID, condition=kind, render_mode=None)
        episodes = []
        for i in range(args.rooms):
            ep = run_episode(policy, pre, post, env, args.seed + i)
            base = env.unwrapped
            ep.update(mask=base.mask, task=base.task, conditions=list(base.conditions))
            episodes.append(ep)
        env.close()
        results[kind] = episodes
        summary[kind] = {
            "success": sum(bool(e["info"]["is_success"]) for e in episodes),
            "collisions": sum(bool(e["info"]["collision"]) for e in episodes),
            "episodes": len(episodes),
            "max_condition_error_m": round(float(np.nanmax([e["info"]["condition_errors"] for e in episodes])), 4),
            "mean_sigma_m": round(float(np.mean([e["std"].mean() for e in episodes])), 4),
        }
        print(f"{kind:>9}: {summary[kind]}")
    summary["figure"] = str(plot(results, args.out))
    summary["checkpoint"] = provenance(args.checkpoint)
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
