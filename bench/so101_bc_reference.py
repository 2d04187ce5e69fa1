"""A plain behaviour-cloning reference on SO-101 pick and place: what an MLP on (τ, state, γ) reaches from a
dataset, to tell a limit of the demonstrations from a limit of CNMP.

    python -m bench.so101_bc_reference [--dataset datasets/cnmp_so101] [--seeds 10 11 12 13] [--episodes 100]

For each seed it trains an MLP (3 x 256, ReLU) from the phase τ = frame / (T - 1), ``observation.state`` and the
episode's first-frame ``observation.environment_state`` (γ) to ``action``, with the mean squared error on
normalized values (Adam 1e-3, cosine to 1e-5, ``--steps`` steps of 256 frames), then runs it closed loop on
``cnmp/SO101PickPlace-v0`` (the wrapper of the third-party plugin's env behind ``--env.type=cnmp_so101``;
extra ``so101``), reset seeds ``--seed`` + i as ``lerobot-eval --seed`` draws them, up to 300 steps, τ
advancing one frame per control step and held at 1. Success is the env's ``is_success``, as ``lerobot-eval``
counts it. It is not a LeRobot policy and is not a method of this project: a yardstick only (the same
objective as CNMP's execution-shaped draws with ``feedback_draw_queries=0``, without the CNP's
encoder / aggregation and with no σ). Several seeds, because one training seed's success spreads by tens of
points on this task. Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from bench.common import REPO, read_frames

DATASET = REPO / "datasets" / "cnmp_so101"
MAX_STEPS = 300


def load_frames(root: Path):
    """(inputs [N, 1 + S + G], actions [N, A], demo length in frames) of every frame of the dataset."""
    df = read_frames(root)
    for key in ("observation.state", "observation.environment_state", "action"):
        if key not in df:
            raise KeyError(f"{root} has no {key!r} column: this bench needs an SO-101 pick-and-place dataset")
    xs, ys, lengths = [], [], []
    for _, ep in df.groupby("episode_index", sort=True):
        state = np.stack(ep["observation.state"].to_numpy())
        gamma = np.stack(ep["observation.environment_state"].to_numpy())[:1]
        n = len(ep)
        if n < 2:
            raise ValueError(f"an episode of {root} has {n} frame(s); the phase needs 2")
        tau = (np.arange(n) / (n - 1))[:, None]
        xs.append(np.concatenate([tau, state, np.repeat(gamma, n, 0)], axis=1))
        ys.append(np.stack(ep["action"].to_numpy()))
        lengths.append(n)
    return np.concatenate(xs).astype(np.float32), np.concatenate(ys).astype(np.float32), int(np.median(lengths))


def train_mlp(x: np.ndarray, y: np.ndarray, seed: int, steps: int):
    """The MLP and its input / output normalization, as a function numpy input -> numpy action."""
    import torch

    torch.manual_seed(seed)
    x_t, y_t = torch.from_numpy(x), torch.from_numpy(y)
    xm, xs = x_t.mean(0), x_t.std(0).clamp(min=1e-6)
    ym, ys = y_t.mean(0), y_t.std(0).clamp(min=1e-6)
    xn, yn = (x_t - xm) / xs, (y_t - ym) / ys
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], 256), torch.nn.ReLU(), torch.nn.Linear(256, 256),
                              torch.nn.ReLU(), torch.nn.Linear(256, 256), torch.nn.ReLU(),
                              torch.nn.Linear(256, y.shape[1]))
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps, 1e-5)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        idx = torch.randint(len(xn), (256,), generator=gen)
        loss = ((net(xn[idx]) - yn[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    net.eval()

    def act(inp: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return (net((torch.from_numpy(inp.astype(np.float32)) - xm) / xs) * ys + ym).numpy()

    return act, loss.item()


def run_episodes(act, env, seed: int, episodes: int, demo_length: int) -> list[bool]:
    out = []
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        gamma = np.asarray(obs["environment_state"], dtype=np.float32).copy()
        success = False
        for k in range(MAX_STEPS):
            tau = min(1.0, k / (demo_length - 1))
            action = act(np.concatenate([[tau], obs["agent_pos"], gamma]))
            obs, _, term, trunc, info = env.step(action.astype(np.float32))
            success |= bool(info.get("is_success"))
            if term or trunc:
                break
        out.append(success)
    return out


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, default=DATASET, help="an SO-101 pick-and-place LeRobotDataset root")
    p.add_argument("--seeds", type=int, nargs="+", default=[10, 11, 12, 13], help="MLP training seeds")
    p.add_argument("--steps", type=int, default=4000, help="training steps per seed (batch 256)")
    p.add_argument("--episodes", type=int, default=100, help="closed-loop episodes per seed")
    p.add_argument("--seed", type=int, default=100000, help="reset seed of the first episode (lerobot-eval's --seed)")
    args = p.parse_args()
    if args.steps < 1 or args.episodes < 1:
        p.error("--steps and --episodes must be >= 1")

    import gymnasium as gym

    import lerobot_cnmp.sims  # noqa: F401  (registers cnmp/SO101PickPlace-v0)

    x, y, demo_length = load_frames(args.dataset)
    env = gym.make("cnmp/SO101PickPlace-v0", render_mode=None)
    print(f"{len(x)} frames from {args.dataset}; demo length {demo_length} frames")
    print(f"{'seed':>5} {'train s':>8} {'final loss':>11} {'success':>10}")
    rows = []
    for s in args.seeds:
        t0 = time.perf_counter()
        act, loss = train_mlp(x, y, s, args.steps)
        train_s = time.perf_counter() - t0
        ok = run_episodes(act, env, args.seed, args.episodes, demo_length)
        rows.append({"seed": s, "train_s": round(train_s, 1), "final_loss": round(loss, 4),
                     "pc_success": round(100.0 * sum(ok) / len(ok), 1)})
        print(f"{s:>5} {train_s:>8.1f} {loss:>11.4f} {rows[-1]['pc_success']:>9.1f}%", flush=True)
    env.close()
    rates = [r["pc_success"] for r in rows]
    print(f"pc_success over {len(rows)} seeds: mean {np.mean(rates):.1f}, min {min(rates):.1f}, max {max(rates):.1f}")
    res = {"dataset": str(args.dataset), "episodes": args.episodes, "seed": args.seed, "steps": args.steps,
           "pc_success_mean": round(float(np.mean(rates)), 1), "runs": rows}
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
