"""Success with RTC (LeRobot's ``RTCInferenceEngine``, chunks in a background thread) vs sync execution
(``lerobot-eval``'s ``rollout``, ``select_action`` every step) on our sims, same checkpoints, same reset seeds.

    python -m bench.rtc_success [--sims obstacle2d,pickplace,weights,room] [--episodes 20] [--seed 100000]

Sync: LeRobot's ``rollout`` (what ``lerobot-eval`` runs). RTC: LeRobot's own ``RTCInferenceEngine`` (the
engine ``lerobot-rollout --inference.type=rtc`` builds) drives the sim as it drives a robot: the control loop
publishes each observation and pops the engine's next action at the sim's fps, in real time; the engine plans
a chunk of ``--chunk`` actions whenever its queue holds at most ``--queue_threshold``, passing RTC's leftover
actions and the measured inference delay to ``CNMPPolicy.predict_action_chunk``. A tick with an empty queue
steps nothing (a robot would hold still). Also a ``no_leftover`` row: the same engine with the leftovers hidden
from the policy (chunks planned from the phase clock alone). Success is the env's flag at any step (as
``lerobot-eval`` counts it); ``largest_step`` is the largest change between consecutive executed actions (env
units), against the demos' largest. Real time: each RTC episode takes its length / fps seconds.
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

import numpy as np
import torch

from bench.common import REPO, make_sim, provenance, resolve_checkpoint

SIMS = {  # name: (EnvConfig class name exported by lerobot_cnmp.sims, default checkpoint, its config)
    "obstacle2d": ("CNMPObstacle2DEnv", "outputs/main", "configs/cnmp_obstacle2d.json"),
    "pickplace": ("CNMPPickPlaceEnv", "outputs/pickplace", "configs/cnmp_pickplace.json"),
    "weights": ("CNMPWeightsEnv", "outputs/weights", "configs/cnmp_weights.json"),
    "room": ("CNMPRoomEnv", "outputs/room", "configs/cnmp_room.json"),  # image-conditioned; start_end
}


def env_config(sim: str):
    from lerobot_cnmp import sims as configs

    return getattr(configs, SIMS[sim][0])(render_mode=None)


def run_sync(policy, pre, post, sim: str, episodes: int, seed: int, batch: int = 10) -> dict:
    """lerobot-eval's rollout: success % over ``episodes`` episodes, seeds ``seed`` + i."""
    from lerobot.scripts.lerobot_eval import rollout

    env, env_pre, env_post = make_sim(env_config(sim), policy, min(batch, episodes))
    n = env.num_envs
    successes, largest = [], 0.0
    try:
        for start in range(0, episodes, n):
            data = rollout(env, policy, env_pre, env_post, pre, post, seeds=list(range(seed + start, seed + start + n)))
            done = data["done"].cumsum(1) <= 1  # the steps up to and including each episode's end
            successes += (data["success"] & done).any(1)[: episodes - start].tolist()
            act = data["action"].numpy()
            steps = np.abs(np.diff(act, axis=1)).max(-1) * (done[:, 1:].numpy())
            largest = max(largest, float(steps.max()))
    finally:
        env.close()
    return {"success": 100.0 * float(np.mean(successes)), "largest_step": largest, "episodes": len(successes)}


class _Robot:
    """What RTCInferenceEngine reads from its robot wrapper."""

    robot_type = "cnmp_sim"

    def __init__(self, action_names):
        self.action_features = {n: float for n in action_names}


def _flat(obs: dict, pixels: dict | None = None) -> tuple[dict, dict]:
    """A LeRobot observation batch of 1 ({"observation.state": [1, n], ...}) as a robot's flat {name: value}
    dict and the matching hardware features (names ``<key>.<i>``); ``pixels`` (the env's raw HWC uint8
    frames by camera) go in as a robot's cameras do (LeRobot's engine scales and permutes them)."""
    flat, hw = {}, {}
    for cam, img in (pixels or {}).items():
        flat[cam] = np.asarray(img)
        hw[f"observation.images.{cam}"] = {"dtype": "image", "shape": tuple(flat[cam].shape),
                                          "names": ["height", "width", "channels"]}
    for key, x in obs.items():
        if not key.startswith("observation.") or key.startswith("observation.images.") or \
                not isinstance(x, torch.Tensor):
            continue
        v = x.reshape(-1).float().numpy()
        names = [f"{key}.{i}" for i in range(v.size)]
        hw[key] = {"dtype": "float32", "shape": (v.size,), "names": names}
        flat.update({n: float(a) for n, a in zip(names, v, strict=True)})
    return flat, hw


def run_rtc(policy, pre, post, sim: str, episodes: int, seed: int, chunk: int, horizon: int, threshold: int,
            leftovers: bool = True) -> dict:
    """The sim driven by LeRobot's RTCInferenceEngine in real time, one episode after another."""
    import gymnasium as gym
    from lerobot.envs.utils import preprocess_observation
    from lerobot.policies.rtc.configuration_rtc import RTCConfig
    from lerobot.rollout.inference import RTCInferenceEngine

    import lerobot_cnmp.sims  # noqa: F401  (registers the gym ids)

    from lerobot.envs.factory import make_env_pre_post_processors

    cfg = env_config(sim)
    env = gym.make(cfg.gym_id, disable_env_checker=True, **cfg.gym_kwargs)
    env_pre, _ = make_env_pre_post_processors(cfg, policy.config)  # as lerobot-eval applies it

    def observe(o, features: bool = False):
        batched = {k: ({n: v[None] for n, v in x.items()} if isinstance(x, dict) else x[None]) for k, x in o.items()}
        out = _flat(env_pre(preprocess_observation(batched)), o.get("pixels"))
        return out if features else out[0]

    fps = float(cfg.fps)
    policy.config.execution.n_action_steps = chunk
    original = policy.predict_action_chunk
    chunks = []

    def planner(batch, inference_delay=0, prev_chunk_left_over=None, **kw):
        chunks.append((inference_delay, prev_chunk_left_over is not None))
        return original(batch, inference_delay=inference_delay,
                        prev_chunk_left_over=prev_chunk_left_over if leftovers else None, **kw)

    policy.predict_action_chunk = planner
    obs, _ = env.reset(seed=seed)
    _, hw = observe(obs, features=True)
    n_act = int(np.prod(env.action_space.shape))
    engine = RTCInferenceEngine(policy, pre, post, _Robot([f"a{i}" for i in range(n_act)]),
                                RTCConfig(execution_horizon=horizon), hw, task="", fps=fps, device="cpu",
                                rtc_queue_threshold=threshold)
    successes, largest, idle_ticks, ticks_total = [], 0.0, 0, 0
    engine.start()
    try:
        for i in range(episodes):
            engine.pause()
            time.sleep(0.05)  # let an inference in flight finish before the reset
            obs, _ = env.reset(seed=seed + i)
            engine.reset()
            engine.notify_observation(observe(obs))
            engine.resume()
            success, prev, t0, tick, done = False, None, time.perf_counter(), 0, False
            max_ticks = 3 * env.spec.max_episode_steps if env.spec and env.spec.max_episode_steps else 3000
            while not done and tick < max_ticks and not engine.failed:
                a = engine.get_action(None)
                tick += 1
                if a is None:
                    idle_ticks += 1
                else:
                    a = a.reshape(-1).numpy().astype(np.float32)
                    if prev is not None:
                        largest = max(largest, float(np.abs(a - prev).max()))
                    prev = a
                    obs, _, terminated, truncated, info = env.step(a)
                    success = success or bool(info.get("is_success", False))
                    done = terminated or truncated
                    engine.notify_observation(observe(obs))
                time.sleep(max(0.0, t0 + tick / fps - time.perf_counter()))  # the control loop's pace
            ticks_total += tick
            if engine.failed:
                raise RuntimeError(f"{sim}: LeRobot's RTC engine failed (see its log)")
            if not done:
                raise RuntimeError(f"{sim}: an RTC episode did not end within {max_ticks} ticks")
            successes.append(success)
    finally:
        engine.stop()
        env.close()
        policy.predict_action_chunk = original
    return {"success": 100.0 * float(np.mean(successes)), "largest_step": largest, "episodes": len(successes),
            "chunks": len(chunks), "chunks_with_leftovers": sum(c[1] for c in chunks),
            "max_inference_delay_steps": max((c[0] for c in chunks), default=0),
            "idle_ticks_pct": round(100.0 * idle_ticks / max(ticks_total, 1), 2)}


def demo_largest_step(sim: str, ckpt: Path) -> float | None:
    """The largest change between consecutive actions in the checkpoint's training demos (env units)."""
    from lerobot_cnmp.data.demos import load_demos

    train_cfg = Path(ckpt) / "train_config.json"
    if not train_cfg.is_file():
        return None
    root = json.loads(train_cfg.read_text())["dataset"].get("root")
    if not root or not Path(root).exists():
        return None
    demos = load_demos(root)["demos"]
    return float(max(np.abs(np.diff(d, axis=0)).max() for d in demos))


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sims", default="obstacle2d,pickplace,weights,room")
    p.add_argument("--checkpoints", default="", help="sim=path,... overriding the defaults (outputs/<sim>/train/...)")
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--seed", type=int, default=100000)
    p.add_argument("--chunk", type=int, default=40, help="actions per chunk (execution.n_action_steps)")
    p.add_argument("--horizon", type=int, default=10, help="RTCConfig.execution_horizon")
    p.add_argument("--queue_threshold", type=int, default=20, help="plan the next chunk at this many queued actions")
    args = p.parse_args()
    if args.episodes < 1:
        p.error("--episodes must be >= 1")
    sims = [s for s in args.sims.split(",") if s]
    unknown = [s for s in sims if s not in SIMS]
    if unknown:
        p.error(f"unknown sims {unknown}; choose from {list(SIMS)}")
    given = dict(kv.split("=", 1) for kv in args.checkpoints.split(",") if kv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    torch.set_num_threads(1)
    # LeRobot's queue warns at every merge whose consumed count differs from the measured delay by a step (the
    # delay is rounded up from the latency); the figures below report the delays themselves
    logging.getLogger("lerobot.policies.rtc.action_queue").setLevel(logging.ERROR)
    from lerobot_cnmp.api import load_pretrained

    out = {}
    for sim in sims:
        _, out_dir, config_path = SIMS[sim]
        ckpt = resolve_checkpoint(given.get(sim, REPO / out_dir / "train/checkpoints/last/pretrained_model"),
                                  train=False, out_dir=REPO / out_dir, config_path=REPO / config_path)
        policy, pre, post = load_pretrained(ckpt)
        policy.eval()
        row = {"sync": run_sync(policy, pre, post, sim, args.episodes, args.seed)}
        for name, leftovers in (("rtc", True), ("rtc_no_leftover", False)):
            policy, pre, post = load_pretrained(ckpt)
            policy.eval()
            row[name] = run_rtc(policy, pre, post, sim, args.episodes, args.seed, args.chunk, args.horizon,
                                args.queue_threshold, leftovers)
        row["demo_largest_step"] = demo_largest_step(sim, ckpt)
        row["checkpoint"] = provenance(ckpt)
        out[sim] = row
        print(f"{sim}: " + ", ".join(f"{k} {row[k]['success']:.0f} % (largest step {row[k]['largest_step']:.3f})"
                                     for k in ("sync", "rtc", "rtc_no_leftover"))
              + f"; demos' largest step {row['demo_largest_step']}", flush=True)
    print(f"\n{'sim':<12}{'mode':<18}{'success %':>10}{'largest step':>14}{'chunks':>8}{'idle %':>8}"
          f"   ({args.episodes} episodes each, seeds {args.seed}+i)")
    for sim, row in out.items():
        for mode in ("sync", "rtc", "rtc_no_leftover"):
            r = row[mode]
            print(f"{sim:<12}{mode:<18}{r['success']:>10.1f}{r['largest_step']:>14.4f}{r.get('chunks', '-'):>8}"
                  f"{r.get('idle_ticks_pct', '-'):>8}")
    res = {"sims": out, "episodes": args.episodes, "seed": args.seed, "chunk": args.chunk, "horizon": args.horizon,
           "queue_threshold": args.queue_threshold,
           "bar": {sim: bool(row["rtc"]["success"] >= row["sync"]["success"] - 100.0 / args.episodes)
                   for sim, row in out.items()},
           "bar_rule": "RTC success within one episode of sync's"}
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
