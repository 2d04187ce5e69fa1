"""Why SO-101 pick and place episodes fail: where the gripper closed, relative to the block, in each episode.

    python -m bench.so101_failures [--checkpoint CKPT | --train] [--episodes 50] [--seed 100000]

Runs a CNMP checkpoint (or a contextual ProMP one, ``lerobot-cnmp-fit-promp``) on ``cnmp/SO101PickPlace-v0``
(the third-party plugin's env behind ``--env.type=cnmp_so101``; extra ``so101``) one episode at a time, reset
seeds ``--seed`` + i as ``lerobot-eval --seed`` draws them, each observation through the policy's processors as
``lerobot-eval`` does. Per episode it records the step at which the policy first commands the jaw closed
(``grasp`` < 0.5) and, at that step, the end effector's offset from the block centre (``agent_pos`` dims 11-13
minus the block's position in ``environment_state``), the block's highest lift and whether the episode
succeeded. The same offsets in the dataset's demos (their first closing frame) are the reference: the plugin's
controller closes at one offset, to about a millimetre.

Classes of a failure: ``closed high`` (the jaw closed more than 2 cm above the block centre, the demos close
at ~1.3 cm, and the block was never lifted), ``dropped`` (lifted, not placed), ``other``. Per episode also the
step at which the jaw reopens and the block's horizontal distance from the goal then (the demos' for reference:
a drop far from the goal is an early release). Last line: one JSON object (``checkpoint`` names the checkpoint).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bench.common import (REPO, add_checkpoint_args, add_episode_args, load_checkpoint_policy, parse_episode_args,
                          policy_batch, provenance, read_frames)

CONFIG = REPO / "configs" / "cnmp_so101.json"
DATASET = REPO / "datasets" / "cnmp_so101"
CHECKPOINT = REPO / "outputs" / "so101" / "train" / "checkpoints" / "last" / "pretrained_model"
EE = slice(11, 14)  # agent_pos: end-effector x, y, z
GRASP = 3  # action: jaw command, 1 open, 0 closed
HIGH_M = 0.02
MAX_STEPS = 300


def goal_distance(env_state) -> float:
    """The block's horizontal distance (m) from the goal in an ``environment_state`` (block x, y, z, goal x, y, z)."""
    return float(np.linalg.norm(env_state[:2] - env_state[3:5]))


def demo_grasps(root: Path) -> tuple[np.ndarray, np.ndarray]:
    """The demos' reference, in one read of the dataset: [episodes, 3] end-effector minus block centre at each
    demo's first closing frame, and [episodes, 2] the step at which its jaw reopens after that and the block's
    distance from the goal then (:func:`goal_distance`)."""
    df = read_frames(root)
    offsets, releases = [], []
    for _, g in df.groupby("episode_index"):
        act, state = np.stack(g["action"].values), np.stack(g["observation.state"].values)
        env = np.stack(g["observation.environment_state"].values)
        closed = np.flatnonzero(act[:, GRASP] < 0.5)
        if closed.size:
            k = int(closed[0])
            offsets.append(state[k, EE] - env[k, :3])
            reopened = np.flatnonzero(act[k:, GRASP] >= 0.5)
            if reopened.size:
                j = k + int(reopened[0])
                releases.append((j, goal_distance(env[j])))
    return np.array(offsets, dtype=float), np.array(releases, dtype=float)


def run_episode(policy, pre, post, env, seed: int) -> dict:
    import torch

    obs, _ = env.reset(seed=seed)
    policy.reset()
    z0 = float(obs["environment_state"][2])
    close_step, offset, lift, success = None, None, 0.0, False
    open_step, open_dist = None, None
    for k in range(MAX_STEPS):
        batch = policy_batch(pre, obs)
        with torch.no_grad():
            action = post(policy.select_action(batch))[0].numpy()
        if close_step is None and action[GRASP] < 0.5:
            close_step, offset = k, (obs["agent_pos"][EE] - obs["environment_state"][:3]).astype(float)
        elif close_step is not None and open_step is None and action[GRASP] >= 0.5:
            # the jaw reopens: where the block is then, horizontally, from the goal
            open_step, open_dist = k, goal_distance(obs["environment_state"])
        obs, _, term, trunc, info = env.step(action.astype(np.float32))
        lift = max(lift, float(obs["environment_state"][2]) - z0)
        success |= bool(info.get("is_success"))
        if term or trunc:
            break
    if success:
        kind = "success"
    elif lift < 0.01 and offset is not None and offset[2] > HIGH_M:
        kind = "closed high"
    elif lift >= 0.01:
        kind = "dropped"
    else:
        kind = "other"
    return {"seed": seed, "kind": kind, "close_step": close_step, "lift_m": round(lift, 4),
            "offset_m": None if offset is None else np.round(offset, 4).tolist(), "open_step": open_step,
            "open_goal_dist_m": None if open_dist is None else round(open_dist, 4)}


def load_policy(args):
    """(checkpoint, policy, preprocessor, postprocessor): a CNMP checkpoint as the other benches load it, or a
    contextual ProMP one (``lerobot-cnmp-fit-promp``, ``--policy.type=promp``), run through the same loop."""
    config = Path(args.checkpoint) / "config.json"
    if args.train or not config.is_file() or json.loads(config.read_text()).get("type") != "promp":
        return load_checkpoint_policy(args, "cnmp_so101", CONFIG)
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_cnmp.promp.modeling_promp import ProMPPolicy

    policy = ProMPPolicy.from_pretrained(args.checkpoint)
    policy.eval()
    pre, post = make_pre_post_processors(policy.config, pretrained_path=args.checkpoint)
    return Path(args.checkpoint), policy, pre, post


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_checkpoint_args(p, CHECKPOINT, "a CNMP (or contextual ProMP) checkpoint fitted on datasets/cnmp_so101")
    add_episode_args(p, seed=100000)
    args = parse_episode_args(p)

    import gymnasium as gym

    import lerobot_cnmp.sims  # noqa: F401  (registers cnmp/SO101PickPlace-v0)

    ckpt, policy, pre, post = load_policy(args)
    env = gym.make("cnmp/SO101PickPlace-v0", render_mode=None)
    demos, releases = demo_grasps(DATASET)
    print(f"demos' offset at closing (x, y, z, m): mean {np.round(demos.mean(0), 4).tolist()}, "
          f"std {np.round(demos.std(0), 4).tolist()} over {len(demos)} demos")
    print(f"{'seed':>7} {'result':<12}{'close step':>11}  {'offset x, y, z (m)':<26}{'lift (m)':>9}")
    runs = []
    for i in range(args.episodes):
        r = run_episode(policy, pre, post, env, args.seed + i)
        runs.append(r)
        off = "-" if r["offset_m"] is None else ", ".join(f"{v:+.3f}" for v in r["offset_m"])
        print(f"{r['seed']:>7} {r['kind']:<12}{str(r['close_step']):>11}  {off:<26}{r['lift_m']:>9.3f}", flush=True)
    env.close()
    kinds = {k: sum(r["kind"] == k for r in runs) for k in ("success", "closed high", "dropped", "other")}

    def mean_offset(sel):
        offs = [r["offset_m"] for r in runs if sel(r) and r["offset_m"] is not None]
        return np.round(np.mean(offs, 0), 4).tolist() if offs else None

    res = {"checkpoint": provenance(ckpt), "episodes": args.episodes, "seed": args.seed,
           "pc_success": round(100.0 * kinds["success"] / args.episodes, 1), "counts": kinds,
           "demo_offset_mean_m": np.round(demos.mean(0), 4).tolist(),
           "demo_offset_std_m": np.round(demos.std(0), 4).tolist(),
           "offset_mean_success_m": mean_offset(lambda r: r["kind"] == "success"),
           "offset_mean_closed_high_m": mean_offset(lambda r: r["kind"] == "closed high"), "runs": runs}
    print(f"success {kinds['success']} / {args.episodes}; failures: closed high {kinds['closed high']}, "
          f"dropped {kinds['dropped']}, other {kinds['other']}; mean offset at closing: successes "
          f"{res['offset_mean_success_m']}, closed high {res['offset_mean_closed_high_m']} (demos "
          f"{res['demo_offset_mean_m']})")
    res["demo_open_step_mean"] = round(float(releases[:, 0].mean()), 1)
    res["demo_open_goal_dist_m_max"] = round(float(releases[:, 1].max()), 4)
    for kind in ("success", "dropped"):
        dists = [r["open_goal_dist_m"] for r in runs if r["kind"] == kind and r["open_goal_dist_m"] is not None]
        res[f"open_goal_dist_m_mean_{kind}"] = round(float(np.mean(dists)), 4) if dists else None
    print(f"jaw reopened with the block from the goal (m, mean): successes {res['open_goal_dist_m_mean_success']}, "
          f"dropped {res['open_goal_dist_m_mean_dropped']} (demos: at most {res['demo_open_goal_dist_m_max']}, "
          f"step {res['demo_open_step_mean']} on average)")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
