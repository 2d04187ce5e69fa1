"""Sensorimotor classification in closed loop with a mid-motion weight switch, as in the paper's Fig. 11.

    python -m bench.weights_fig11 [--checkpoint CKPT] [--shape 0|1] [--mass KG] [--seed N] [--out PNG]

Runs the trained CNMP in ``cnmp_weights`` with ``perturbation=weight_switch`` (a light container becomes
heavy during transport) for one episode, with the config's execution settings (online feedback, PD,
phase stop). At every step it also asks the CNMP, conditioned as the executor is at that step, for the SM
at the end of the motion (phase 1): the predicted end position (x, y) with its σ. The figure shows
(left) the four zones, the executed tool path and the predicted end distribution (μ ± 2σ) before the
grasp, after the lift and after the switch; (right) the phase against the control step, which stalls
while the arm is redirected after the switch, and the predicted end y. A missing checkpoint is an error;
with ``--train`` the config's CNMP is fitted with the API first. Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bench.common import REPO, add_checkpoint_args, checkpoint_from_args, policy_batch, predict_sm, provenance

CONFIG = REPO / "configs" / "cnmp_weights.json"
CHECKPOINT = REPO / "outputs" / "weights" / "train" / "checkpoints" / "last" / "pretrained_model"
OUT = REPO / "docs" / "fig11_weights.png"
AFTER = 15  # steps after the lift / the switch at which the prediction is shown


def run_episode(policy, pre, post, env, shape: int, mass: float, seed: int, max_steps: int) -> dict:
    """One closed-loop episode; per step the phase, the sensed SM and the predicted end (μ, σ) of (x, y)."""
    import torch

    obs, info = env.reset(seed=seed, options={"shape": shape, "mass": mass})
    policy.reset()
    log = {"phase": [], "state": [], "end_mean": [], "end_std": [], "lifted": [], "switched": []}
    for _ in range(max_steps):
        batch = policy_batch(pre, obs)
        with torch.no_grad():
            action = policy.select_action(batch)
        mean, std = predict_sm(policy, pre, post, batch, policy.executor.phase, [1.0])  # the end, as the executor sees it
        log["phase"].append(float(policy.executor.phase[0]))
        log["state"].append(obs["agent_pos"].copy())
        log["end_mean"].append(mean[0, :2])
        log["end_std"].append(std[0, :2])
        log["lifted"].append(bool(info["lifted"]))
        log["switched"].append(bool(info["weight_switched"]))
        obs, _, terminated, truncated, info = env.step(post(action)[0].numpy())
        if terminated or truncated:
            break
    out = {k: np.asarray(v) for k, v in log.items()}
    out["info"] = info
    return out


def plot(log: dict, out: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse, Rectangle

    from lerobot_cnmp.sims.weights.task import PICK_XY, ZONE_HALF, ZONE_RGBA, ZONE_XY

    moments = moments_of(log)
    fig, (ax, axp) = plt.subplots(1, 2, figsize=(11, 4.6), gridspec_kw={"width_ratios": [1, 1.25]})
    for z, (xy, rgba) in enumerate(zip(ZONE_XY, ZONE_RGBA)):
        ax.add_patch(Rectangle(xy - ZONE_HALF, 2 * ZONE_HALF, 2 * ZONE_HALF, color=rgba, alpha=0.35))
        ax.text(*xy, ("narrow", "narrow", "wide", "wide")[z] + "\n" + ("light", "heavy")[z % 2], ha="center",
                va="center", fontsize=7)
    ax.add_patch(Rectangle(PICK_XY - 0.04, 0.08, 0.08, color="0.6", alpha=0.4))
    s = log["state"]
    ax.plot(s[:, 0], s[:, 1], "k-", lw=1, label="executed tool path")
    colors = {"before grasp": "tab:gray", "after lift": "tab:orange", "after switch": "tab:red"}
    for name, k in moments.items():
        m, sd = log["end_mean"][k], log["end_std"][k]
        ax.add_patch(Ellipse(m, 4 * sd[0], 4 * sd[1], fill=False, color=colors[name], lw=2))
        ax.plot(*m, "o", color=colors[name], label=f"{name} (step {k}): μ ± 2σ")
    ax.set_xlim(0.3, 1.1)
    ax.set_ylim(-0.45, 0.75)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("predicted end position")
    ax.legend(fontsize=7, loc="lower right")
    steps = np.arange(len(log["phase"]))
    axp.plot(steps, log["phase"], "k-", label="phase τ")
    axp.set_xlabel("control step")
    axp.set_ylabel("phase τ")
    ax2 = axp.twinx()
    ax2.plot(steps, log["end_mean"][:, 1], color="tab:blue", label="predicted end y")
    ax2.fill_between(steps, log["end_mean"][:, 1] - 2 * log["end_std"][:, 1],
                     log["end_mean"][:, 1] + 2 * log["end_std"][:, 1], color="tab:blue", alpha=0.2)
    ax2.set_ylabel("predicted end y (m)", color="tab:blue")
    for name, k in moments.items():
        axp.axvline(k, color=colors[name], ls="--", lw=1)
    if log["switched"].any():
        axp.axvline(int(np.argmax(log["switched"])), color="tab:red", lw=2, label="weight added")
    axp.legend(loc="upper left", fontsize=7)
    axp.set_title("phase (stalls while redirected) and predicted end")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    from lerobot_cnmp.plot import save_figure

    return save_figure(fig, out, dpi=110)


def moments_of(log: dict) -> dict:
    """Steps at which the figure shows the prediction: at the start, AFTER steps after the lift and after
    the switch."""
    lifted, switched = log["lifted"], log["switched"]
    n = len(lifted)
    out = {"before grasp": 0}
    if lifted.any():
        out["after lift"] = min(int(np.argmax(lifted)) + AFTER, n - 1)
    if switched.any():
        out["after switch"] = min(int(np.argmax(switched)) + AFTER, n - 1)
    return out


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_checkpoint_args(p, CHECKPOINT, "a CNMP checkpoint trained on cnmp_weights")
    p.add_argument("--shape", type=int, default=1)
    p.add_argument("--mass", type=float, default=0.225)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args()

    from lerobot_cnmp.api import load_pretrained
    from lerobot_cnmp.sims.weights.config import CNMPWeightsEnv
    from lerobot_cnmp.sims.weights.env import WeightsEnv
    from lerobot_cnmp.sims.weights.task import SHAPES

    ckpt = checkpoint_from_args(args, "cnmp_weights", config_path=CONFIG)
    policy, pre, post = load_pretrained(ckpt)
    policy.eval()
    env = WeightsEnv(perturbation="weight_switch", render_mode=None, terminate_on_success=True)
    log = run_episode(policy, pre, post, env, args.shape, args.mass, args.seed, CNMPWeightsEnv().episode_length)
    info = log["info"]
    moments = moments_of(log)
    res = {
        "checkpoint": provenance(ckpt),
        "success": bool(info["is_success"]),
        "steps": len(log["phase"]),
        "switch_step": int(info["switch_step"]),
        "final_mass_kg": round(float(info["mass"]), 4),
        "target_zone": int(info["target_zone"]),
        "object_zone": int(info["object_zone"]),
        "end_sigma_m": {k: [round(float(v), 4) for v in log["end_std"][s]] for k, s in moments.items()},
        "end_mean_m": {k: [round(float(v), 3) for v in log["end_mean"][s]] for k, s in moments.items()},
        "phase_stalled_steps": int(np.sum(np.diff(log["phase"]) == 0.0) - np.sum(np.asarray(log["phase"][1:]) >= 1.0)),
    }
    title = (f"{SHAPES[args.shape][0]}, {args.mass:g} kg + weight switch at step {res['switch_step']} -> "
             f"{res['final_mass_kg']:g} kg; placed on zone {res['object_zone']} (target {res['target_zone']}), "
             f"success {res['success']}")
    res["figure"] = str(plot(log, args.out, title))
    for name, s in moments.items():
        print(f"{name:>13} (step {s:3d}): predicted end (x, y) = {res['end_mean_m'][name]} m, "
              f"σ = {res['end_sigma_m'][name]} m")
    print(f"phase stalled for {res['phase_stalled_steps']} steps; {title}")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
