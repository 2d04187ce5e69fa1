"""Latency of one control step (condition on the goals + the current state, predict the next SM target).

    python -m bench.latency [--calls 2000]

Figures on CPU with 1 torch thread, same policy and observation stream, p50 over ``--calls`` calls:
- ``control_step_p50_ms``: in-process, the network the policy executes (``CNMPPolicy.network()``: on
  CPU the numpy copy ``NumpyCNMP``) on a ready context of the policy's execution (2 conditions, the start
  state, the sensed state), one query: encode + aggregate + decode;
- ``trajectory_200_ms``: the same context, a whole 200-step trajectory with σ (200 queries in one call);
- ``*_torch_*``: the same two with the torch model (``--policy.numpy_execution=false``, and training);
- ``select_action_p50_ms``: what ``lerobot-eval`` runs per step: preprocessor (normalize, batch, device) ->
  ``CNMPPolicy.select_action`` -> postprocessor (unnormalize);
- ``chunk_50_p50_ms``: preprocessor -> ``CNMPPolicy.predict_action_chunk`` of 50 steps with σ
  (``return_std=True``), what LeRobot's RTC engine and the async server call.
Bars (issue 15): select_action with processors p50 <= 0.5 ms, a 50-step chunk with σ <= 1 ms (``bars``).

    python -m bench.latency --camera 128

The CNMP that sees (issue 37): a policy with one ``--camera`` x ``--camera`` RGB image feature and the conv encoder
of ``configs/cnmp_metaworld_push_cam.json`` (MetaWorld's 4-dim hand state and action), untrained. The encoder
runs once per episode, on its first frame (as in training); ``select_action_p50_ms`` is the p50 over episodes of
``--episode_steps`` steps, each episode's first step included (``first_step_p50_ms``: that step alone, the encoder's
cost). Bar: select_action p50 <= 2 ms with one 128 x 128 camera.
The calls run in ``--rounds`` interleaved rounds; the spread of the round p50s shows how much the machine
itself moved during the run. Latency does not depend on the weights, so the policy is built from the
dataset without training.
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]


def timings_ms(fn, calls: int) -> np.ndarray:
    times = np.empty(calls)
    for i in range(calls):
        t0 = time.perf_counter()
        fn()
        times[i] = time.perf_counter() - t0
    return times * 1e3


def interleaved_p50(fns: dict, calls: int, rounds: int) -> dict:
    """{name: (p50 over all calls, [p50 of each round])}, the functions taking turns round by round."""
    for fn in fns.values():
        timings_ms(fn, 100)  # warm-up
    per = {name: [] for name in fns}
    for _ in range(rounds):
        for name, fn in fns.items():
            per[name].append(timings_ms(fn, max(calls // rounds, 1)))
    return {name: (float(np.median(np.concatenate(t))), [float(np.median(x)) for x in t]) for name, t in per.items()}


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--calls", type=int, default=3000)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--dataset", default=str(REPO / "datasets" / "cnmp_obstacle2d"))
    p.add_argument("--camera", type=int, default=None, help="side of one camera image: the image CNMP's latency")
    p.add_argument("--episode_steps", type=int, default=150, help="with --camera: steps per episode")
    args = p.parse_args()
    torch.set_num_threads(1)
    if args.camera:
        return camera_latency(args.camera, args.calls, args.episode_steps)

    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy
    from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE

    from lerobot_cnmp.execution.conditions import Condition, encode_conditions
    from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig
    from lerobot_cnmp.policy.processor_cnmp import make_cnmp_pre_post_processors

    meta = LeRobotDatasetMetadata("lerobot-cnmp/cnmp_obstacle2d", root=args.dataset)
    cfg = CNMPConfig(device="cpu", state_tracks_action=True)  # the obstacle sim: SM = action, state reaches it
    policy = make_policy(cfg, ds_meta=meta).eval()
    pre, post = make_cnmp_pre_post_processors(cfg, meta.stats)

    env_state = encode_conditions([Condition(0.5, (0.5, 0.4)), Condition(1.0, (1.0, 0.13))], 2, 4)
    obs = {OBS_STATE: torch.tensor([[0.1, 0.13]]), OBS_ENV_STATE: torch.from_numpy(env_state)[None]}

    # In-process: the context the policy builds each step, then the network alone.
    policy.reset()
    ctx = policy.executor.execution_context(pre(dict(obs)), torch.full((1,), 0.3))
    query = torch.full((1, 1), 0.3)
    trajectory = torch.linspace(0, 1, 200)[None]

    executor = policy.network()

    def control_step():
        executor(ctx, query)

    def trajectory_200():
        executor(ctx, trajectory)

    def control_step_torch():
        with torch.inference_mode():
            policy.model(ctx, query)

    def trajectory_200_torch():
        with torch.inference_mode():
            policy.model(ctx, trajectory)

    def select_action():
        with torch.inference_mode():
            post(policy.select_action(pre(dict(obs))))

    def chunk_50():
        with torch.inference_mode():
            policy.predict_action_chunk(pre(dict(obs)), n_steps=50, return_std=True)

    policy.reset()
    fns = {"control_step": control_step, "trajectory_200": trajectory_200, "select_action": select_action,
           "chunk_50": chunk_50,
           "control_step_torch": control_step_torch, "trajectory_200_torch": trajectory_200_torch}
    t = interleaved_p50(fns, args.calls, args.rounds)
    res = {
        "control_step_p50_ms": round(t["control_step"][0], 4),
        "trajectory_200_ms": round(t["trajectory_200"][0], 4),
        "select_action_p50_ms": round(t["select_action"][0], 4),
        "chunk_50_p50_ms": round(t["chunk_50"][0], 4),
        "bars": {"select_action_p50_ms <= 0.5": bool(t["select_action"][0] <= 0.5),
                 "chunk_50_p50_ms <= 1.0": bool(t["chunk_50"][0] <= 1.0)},
        "control_step_torch_p50_ms": round(t["control_step_torch"][0], 4),
        "trajectory_200_torch_ms": round(t["trajectory_200_torch"][0], 4),
        "executor": type(executor).__name__,
        "timed": {
            "control_step_p50_ms": f"network alone ({type(executor).__name__}): encode + aggregate + decode of a ready "
                                   "context, 1 query; no processors, no context building",
            "trajectory_200_ms": f"network alone ({type(executor).__name__}), 200 queries in one call",
            "control_step_torch_p50_ms": "network alone, torch model (inference_mode), 1 query",
            "trajectory_200_torch_ms": "network alone, torch model, 200 queries",
            "select_action_p50_ms": "the whole lerobot-eval step: preprocessor + CNMPPolicy.select_action (context "
                                    "building, phase update, network, PD) + postprocessor",
        },
        "checkpoint": {"path": None, "step": 0, "training_command": None,
                       "trained_by": "none: an untrained CNMPConfig() policy with the dataset's statistics "
                                     "(latency does not depend on the weights)"},
        **{f"{k}_round_p50s_ms": [round(v, 4) for v in t[k][1]] for k in fns},
        "calls": args.calls,
        "context_points": int(ctx.valid.sum()),
        "torch_threads": torch.get_num_threads(),
        "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} torch thread(s), CPU",
    }
    labels = {"control_step": "network alone, 1 query", "trajectory_200": "network alone, 200 queries + σ",
              "select_action": "select_action + processors", "chunk_50": "50-step chunk + σ + processors",
              "control_step_torch": "network alone, torch",
              "trajectory_200_torch": "network alone, torch, 200q"}
    print(f"{'figure':<26}{'p50 (ms)':>10}   rounds' p50s")
    for k, label in labels.items():
        print(f"{label:<26}{t[k][0]:>10.4f}   {' '.join(f'{v:.3f}' for v in t[k][1])}")
    print(json.dumps(res))
    return res


def camera_latency(size: int, calls: int, episode_steps: int) -> dict:
    """select_action of an image CNMP (one size x size camera): the first step of an episode encodes the image."""
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

    from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig
    from lerobot_cnmp.policy.image_config import ImageEncoderConfig
    from lerobot_cnmp.policy.modeling_cnmp import CNMPPolicy
    from lerobot_cnmp.policy.processor_cnmp import make_cnmp_pre_post_processors

    raw = json.loads((REPO / "configs" / "cnmp_metaworld_push_cam.json").read_text())["policy"]
    image = f"{OBS_IMAGES}.camera"
    cfg = CNMPConfig(device="cpu", use_images=True, image_encoder=ImageEncoderConfig(**raw["image_encoder"]),
                     phase_frequencies=raw["phase_frequencies"], demo_duration_s=3.0, dataset_fps=50.0)
    cfg.input_features = {OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(4,)),
                          image: PolicyFeature(type=FeatureType.VISUAL, shape=(3, size, size))}
    cfg.output_features = {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(4,))}
    policy = CNMPPolicy(cfg).eval()
    policy.normalizer.set((np.zeros(8, np.float32), np.ones(8, np.float32)), None)
    pre, post = make_cnmp_pre_post_processors(cfg)
    obs = {OBS_STATE: torch.zeros(1, 4), image: torch.rand(1, 3, size, size)}
    steps, firsts = [], []
    n_episodes = max(1, calls // episode_steps)
    with torch.inference_mode():
        for _ in range(n_episodes):
            policy.reset()
            for k in range(episode_steps):
                t0 = time.perf_counter()
                post(policy.select_action(pre(dict(obs))))
                ms = (time.perf_counter() - t0) * 1e3
                steps.append(ms)
                if k == 0:
                    firsts.append(ms)
    res = {"camera": f"1 x {size} x {size} RGB", "image_encoder": raw["image_encoder"],
           "select_action_p50_ms": round(float(np.median(steps)), 4),
           "first_step_p50_ms": round(float(np.median(firsts)), 4),
           "mean_ms_per_step": round(float(np.mean(steps)), 4),
           "bars": {"select_action_p50_ms <= 2": bool(np.median(steps) <= 2.0)},
           "encoder": "once per episode, on its first step's image (the first frame, as in training)",
           "episodes": n_episodes, "episode_steps": episode_steps, "torch_threads": torch.get_num_threads(),
           "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} torch thread(s), CPU"}
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
