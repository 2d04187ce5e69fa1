"""Does the CNMP that sees use what it sees? The same checkpoint with its cameras, and with each camera replaced
by a constant image (the demos' mean first frame, the encoder's ``mean_image``; mid-gray without one).

    python -m bench.camera_ablation --checkpoint CKPT --task push-v3 --episodes 50

Runs our MetaWorld wrapper with the checkpoint's cameras (``--env.cameras`` of its image features), seeds
``--seed + i`` as ``lerobot-eval --seed`` gives them, through the policy's own processors and ``select_action``
(the loop of ``lerobot-eval``, in-process so the images can be swapped). A policy that ignores the scene succeeds
about as often with the constant image as with the real one; one that reads it falls to the success of a plan
that does not know where the object and the goal are. Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch


def run(policy, pre, post, task: str, cameras: list[str], size: int, episodes: int, seed: int, constant: dict | None,
        ep_len: int = 150) -> float:
    from lerobot_cnmp.sims.metaworld.env import MetaWorldEnv

    env = MetaWorldEnv(task=task, terminate_on_success=True, max_episode_steps=ep_len, cameras=cameras,
                       camera_size=size)
    wins = 0
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        policy.reset()
        for _ in range(ep_len):
            batch = {"observation.state": torch.from_numpy(obs["agent_pos"])[None]}
            for c in cameras:
                key = f"observation.images.{c}"
                img = torch.from_numpy(obs["pixels"][c]).permute(2, 0, 1)[None].float() / 255.0
                batch[key] = constant[key][None] if constant is not None else img
            with torch.inference_mode():
                action = post(policy.select_action(pre(batch)))[0].numpy()
            obs, _, term, trunc, info = env.step(action)
            if term or trunc:
                break
        wins += bool(info["is_success"])
    env.close()
    return 100.0 * wins / episodes


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--task", required=True, help="MetaWorld task, e.g. push-v3")
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--seed", type=int, default=100000)
    p.add_argument("--modes", nargs="+", default=["real", "constant"], choices=["real", "constant"])
    args = p.parse_args(argv)
    torch.set_num_threads(1)

    from lerobot_cnmp.api import load_pretrained

    policy, pre, post = load_pretrained(args.checkpoint, device="cpu")
    policy.eval()
    keys = policy.config.image_keys
    if not keys:
        raise SystemExit(f"error: {args.checkpoint} conditions on no image (use_images is off)")
    cameras = [k.removeprefix("observation.images.") for k in keys]
    size = int(policy.config.input_features[keys[0]].shape[-1])
    constant = {}
    for k in keys:
        mean = policy.image_encoders[k.replace(".", "_")].mean_image
        constant[k] = mean.clone() if mean is not None else torch.full(tuple(policy.config.input_features[k].shape), 0.5)
    res = {"checkpoint": str(args.checkpoint), "task": args.task, "cameras": cameras, "episodes": args.episodes,
           "seed": args.seed, "constant_image": "the demos' mean first frame (mean_image)"
           if policy.image_encoders[keys[0].replace(".", "_")].mean_image is not None else "mid-gray"}
    for mode in args.modes:
        t0 = time.perf_counter()
        res[f"success_{mode}"] = run(policy, pre, post, args.task, cameras, size, args.episodes, args.seed,
                                     constant if mode == "constant" else None)
        res[f"seconds_{mode}"] = round(time.perf_counter() - t0, 1)
        print(f"{mode}: {res[f'success_{mode}']:.1f} % ({res[f'seconds_{mode}']} s)", flush=True)
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
