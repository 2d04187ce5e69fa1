"""Few-demo MetaWorld cells, CNMP vs contextual ProMP: offline proxies (seconds per fit) and, on request, sim success.

Fits CNMP (the task's committed config, trained as ``lerobot-train --dataset.episodes=[0..N-1]`` trains it: the
policy's bank holds every episode, with statistics over all of them, and the training draws name the first N
only) and the contextual ProMP (``ProMPBaseline`` on the first N episodes' actions, conditioned on γ), then
predicts each held-out episode's (30-49) action trajectory from its γ (CNMP also from its first frame's sensed
state, as execution conditions on it at t = 0) and reports the RMSE of the actions, per dim in units of the
dataset's action std, averaged over dims, phases and episodes; also ``rmse_feedback`` (CNMP conditioned on the
demo's own hand state at every phase) and ``drift`` (the running sum of the dx, dy, dz errors: the proxy that
agrees with the sim). ``--sim_episodes`` rolls both out in the MetaWorld sim (seeds 100000+).

    python -m bench.fewdemo_proxy --task push --demos 5 10 20 --steps 3000
    python -m bench.fewdemo_proxy --task push --demos 10 --methods promp cnmp --sim_episodes 50   # + sim success

``--set key=value`` overrides a CNMPConfig field (JSON value) for the one-change experiments; CNMP is built as
``lerobot-train`` builds it, so the rules of ``lerobot_cnmp.policy.rules`` apply (``--set linear_task_term=false``:
the network without the linear-in-γ term).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from bench.compare_cells import METAWORLD_TASKS

REPO = Path(__file__).resolve().parent.parent
HELD_OUT = list(range(30, 50))


def load_episodes(root: Path):
    import pandas as pd

    df = pd.concat([pd.read_parquet(f) for f in sorted((root / "data").glob("*/*.parquet"))])
    eps = {}
    for e, g in df.groupby("episode_index"):
        g = g.sort_values("frame_index")
        eps[int(e)] = {"state": np.stack(g["observation.state"].values).astype(np.float32),
                       "action": np.stack(g["action"].values).astype(np.float32),
                       "gamma": np.asarray(g["observation.task_params"].values[0], np.float32)}
    return eps


def build_cnmp(task: str, overrides: dict):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy

    from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig

    raw = json.loads((REPO / f"configs/cnmp_metaworld_{task}.json").read_text())
    pol = {k: v for k, v in raw["policy"].items() if k not in ("type", "push_to_hub")}
    for k, v in overrides.items():
        head, _, tail = k.partition(".")
        if tail:
            pol.setdefault(head, {})[tail] = v
        else:
            pol[k] = v
    cfg = CNMPConfig(**pol)
    meta = LeRobotDatasetMetadata(raw["dataset"]["repo_id"], root=REPO / raw["dataset"]["root"])
    return make_policy(cfg, ds_meta=meta), raw


def add_gamma_noise(model, sigma: float) -> None:
    """A candidate regularizer, screened here and not in the package: Gaussian noise of std ``sigma`` on the
    normalized γ of every training draw (for the linear term, a ridge in expectation)."""
    import dataclasses

    loss = model.training_loss

    def noisy(context, targets, draws=1):
        if context.task_params is not None:
            context = dataclasses.replace(context, task_params=context.task_params
                                          + sigma * torch.randn_like(context.task_params))
        return loss(context, targets, draws)

    model.training_loss = noisy


def train_cnmp(policy, episodes: list[int], steps: int, batch_size: int, seed: int) -> float:
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    cfg = policy.config
    optim = cfg.get_optimizer_preset().build(policy.get_optim_params())
    sched_cfg = cfg.get_scheduler_preset()
    sched = None if sched_cfg is None else sched_cfg.build(optim, steps)
    ids = torch.tensor(episodes)
    policy.train()
    t0 = time.perf_counter()
    for _ in range(steps):
        batch = {"episode_index": ids[torch.randint(len(ids), (batch_size,), generator=gen)]}
        loss, _ = policy.forward(batch, generator=gen)
        optim.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), cfg.optimizer_grad_clip_norm)
        optim.step()
        if sched is not None:
            sched.step()
    policy.eval()
    return time.perf_counter() - t0


@torch.no_grad()
def cnmp_predict(policy, ep: dict) -> np.ndarray:
    """The mean SM trajectory given γ and the first frame's sensed dims at t = 0, in the dataset's units."""
    from lerobot_cnmp.model.cnmp import Context

    spec, norm = policy.config.spec, policy.normalizer
    T = len(ep["action"])
    sm0 = np.zeros(policy.config.sm_dim, np.float32)
    mask = np.zeros(policy.config.sm_dim, np.float32)
    for i, d in enumerate(spec.dims):
        if d.feature == "observation.state":
            v = ep["state"][0, d.index]
            if d.origin is not None:
                v = v - ep["gamma"][d.origin[1]]
            sm0[i], mask[i] = v, 1.0
    vals = ((torch.from_numpy(sm0) - norm.sm_mean) / norm.sm_std * torch.from_numpy(mask))[None, None]
    gamma = norm.task(torch.from_numpy(ep["gamma"])[None]) if policy.config.task_dim else None
    ctx = Context(torch.zeros(1, 1), vals, torch.from_numpy(mask)[None, None], torch.ones(1, 1, dtype=torch.bool), gamma)
    q = torch.linspace(0, 1, T)[None]
    mean, _ = policy.model(ctx, q)
    return (norm.sm_inverse(mean[0])).numpy()


@torch.no_grad()
def cnmp_feedback(policy, ep: dict) -> np.ndarray:
    """Execution's per-step prediction with the demo's own sensed states (teacher forcing): at each frame k the
    context is the sensed dims at t = 0 and at t_k (as ``online_feedback`` conditions), the output the SM mean
    at t_k. A model that relies on (t, sensed) pairs it never saw errs here, not in the open-loop plan."""
    from lerobot_cnmp.model.cnmp import Context

    spec, norm, d = policy.config.spec, policy.normalizer, policy.config.sm_dim
    T = len(ep["action"])
    sm = np.zeros((T, d), np.float32)
    mask = np.zeros(d, np.float32)
    for i, dim in enumerate(spec.dims):
        if dim.feature == "observation.state":
            v = ep["state"][:, dim.index]
            if dim.origin is not None:
                v = v - ep["gamma"][dim.origin[1]]
            sm[:, i], mask[i] = v, 1.0
    z = (torch.from_numpy(sm) - norm.sm_mean) / norm.sm_std * torch.from_numpy(mask)
    t = torch.linspace(0, 1, T)
    phases = torch.stack([torch.zeros(T), t], 1)
    vals = torch.stack([z[0].expand(T, d), z], 1)
    m = torch.from_numpy(mask).expand(T, 2, d)
    gamma = norm.task(torch.from_numpy(ep["gamma"])[None]).expand(T, -1) if policy.config.task_dim else None
    ctx = Context(phases, vals, m, torch.ones(T, 2, dtype=torch.bool), gamma)
    mean, _ = policy.model(ctx, t[:, None])
    return norm.sm_inverse(mean[:, 0]).numpy()


@torch.no_grad()
def sim_success(policy, task: str, n_episodes: int, seed: int = 100000, ep_len: int = 150) -> tuple[float, dict]:
    """Closed-loop success in the MetaWorld sim (our wrapper, seeds ``seed + i`` as lerobot-eval's), with the
    policy's own execution loop; also the mean final hand-to-goal and object-to-goal distances."""
    from lerobot_cnmp.sims.metaworld.env import MetaWorldEnv

    name = {short: full for full, short in METAWORLD_TASKS.items()}[task]
    env = MetaWorldEnv(task=name, terminate_on_success=True, max_episode_steps=ep_len)
    wins = 0
    for i in range(n_episodes):
        obs, _ = env.reset(seed=seed + i)
        policy.reset()
        for _ in range(ep_len):
            batch = {"observation.state": torch.from_numpy(obs["agent_pos"])[None],
                     "observation.task_params": torch.from_numpy(obs["environment_state"])[None]}
            a = policy.select_action(batch)[0].numpy()
            obs, _, term, trunc, info = env.step(a)
            if term or trunc:
                break
        wins += bool(info["is_success"])
    env.close()
    return 100.0 * wins / n_episodes


class ProMPReplay:
    """The contextual ProMP executed as ``--policy.type=promp`` executes it: the mean action plan given γ, built
    at the episode's first step over the demos' length, replayed open loop."""

    def __init__(self, baseline, steps: int):
        self.baseline, self.steps, self.plan, self.k = baseline, steps, None, 0

    def reset(self):
        self.plan, self.k = None, 0

    def select_action(self, batch):
        if self.plan is None:
            g = batch["observation.task_params"][0].numpy().astype(np.float64)
            self.plan = self.baseline.predict(np.linspace(0, 1, self.steps), [], task_params=g)[0]
        a = self.plan[min(self.k, self.steps - 1)]
        self.k += 1
        return torch.from_numpy(np.asarray(a, np.float32))[None]


def score(pred_actions: list[np.ndarray], eps: dict, act_std: np.ndarray) -> float:
    err = [((p - eps[e]["action"]) / act_std) ** 2 for p, e in zip(pred_actions, HELD_OUT)]
    return float(np.sqrt(np.mean(err)))


def drift(pred_actions: list[np.ndarray], eps: dict) -> float:
    """RMS over phases and held-out episodes of the running sum of the (dx, dy, dz) action errors, in action
    units: where an open-loop plan of delta actions ends up off the demo's path (biases add up, noise does not)."""
    err = [np.cumsum(p[:, :3] - eps[e]["action"][:, :3], 0) ** 2 for p, e in zip(pred_actions, HELD_OUT)]
    return float(np.sqrt(np.mean(err)))


def run(task: str, demos: list[int], steps: int, batch_size: int, seeds: list[int], overrides: dict,
        methods: list[str], sim_episodes: int = 0, open_loop_too: bool = False, gamma_noise: float = 0.0) -> list[dict]:
    from lerobot_cnmp.data import bank
    from lerobot_cnmp.promp.baselines import ProMPBaseline

    eps = load_episodes(REPO / f"datasets/cnmp_metaworld_{task}")
    act_std = np.std(np.concatenate([e["action"] for e in eps.values()]), 0)
    act_std = np.where(act_std > 1e-6, act_std, 1.0)
    rows = []
    for n in demos:
        train = list(range(n))
        if "promp" in methods:
            pm = ProMPBaseline().fit([eps[i]["action"] for i in train], task_params=np.stack([eps[i]["gamma"] for i in train]))
            T = len(eps[HELD_OUT[0]]["action"])
            preds = [pm.predict(np.linspace(0, 1, T), [], task_params=eps[e]["gamma"])[0] for e in HELD_OUT]
            rows.append({"task": task, "n": n, "method": "promp", "rmse": score(preds, eps, act_std),
                         "drift": drift(preds, eps)})
            if sim_episodes:
                rows[-1]["sim_success"] = sim_success(ProMPReplay(pm, T), task, sim_episodes)
            print(json.dumps(rows[-1]), flush=True)
        if "cnmp" in methods:
            for seed in seeds:
                torch.manual_seed(seed)  # the initialization follows the seed too
                policy, _ = build_cnmp(task, overrides)
                if gamma_noise:
                    add_gamma_noise(policy.model, gamma_noise)
                secs = train_cnmp(policy, train, steps, batch_size, seed)
                spec = policy.config.spec
                cmd = list(spec.commanded)
                preds = [cnmp_predict(policy, eps[e])[:, cmd] for e in HELD_OUT]
                fb = [cnmp_feedback(policy, eps[e])[:, cmd] for e in HELD_OUT]
                rows.append({"task": task, "n": n, "method": "cnmp", "seed": seed, "steps": steps,
                             "overrides": overrides, "gamma_noise": gamma_noise,
                             "task_std_floor": bank.TASK_STD_FLOOR, "rmse": score(preds, eps, act_std),
                             "rmse_feedback": score(fb, eps, act_std), "drift": drift(preds, eps), "train_s": round(secs, 1)})
                if sim_episodes:
                    rows[-1]["sim_success"] = sim_success(policy, task, sim_episodes)
                    if open_loop_too:  # the same network replaying its t = 0 plan (no feedback)
                        from lerobot_cnmp.policy.modeling_cnmp import _executor_for

                        policy.config.execution.online_feedback = False
                        policy.executor = _executor_for(policy)
                        rows[-1]["sim_success_open_loop"] = sim_success(policy, task, sim_episodes)
                print(json.dumps(rows[-1]), flush=True)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="push", choices=list(METAWORLD_TASKS.values()))
    p.add_argument("--demos", type=int, nargs="+", default=[5, 10, 20])
    p.add_argument("--steps", type=int, default=9000)
    p.add_argument("--batch_size", type=int, default=8)
    p.add_argument("--seeds", type=int, nargs="+", default=[1000])
    p.add_argument("--methods", nargs="+", default=["cnmp", "promp"])
    p.add_argument("--sim_episodes", type=int, default=0, help="also roll CNMP out in the sim (seeds 100000+)")
    p.add_argument("--open_loop_too", action="store_true", help="also roll out without online feedback")
    p.add_argument("--set", action="append", default=[], help="CNMPConfig override key=JSON value")
    p.add_argument("--gamma_noise", type=float, default=0.0, help="screen: noise std on the normalized γ in training")
    p.add_argument("--task_std_floor", type=float, default=None,
                   help="γ's normalization floor, a fraction of the median γ std (default: the package's "
                        "TASK_STD_FLOOR; 0.01, the SM's floor, is the normalization before 2026-12-07)")
    args = p.parse_args(argv)
    if args.task_std_floor is not None:
        if not np.isfinite(args.task_std_floor) or args.task_std_floor < 0:
            p.error(f"--task_std_floor must be a finite number >= 0, got {args.task_std_floor}")
        from lerobot_cnmp.data import bank

        bank.TASK_STD_FLOOR = args.task_std_floor  # read by EpisodeBank.task_stats when the policy is built
    overrides = {}
    for s in args.set:
        k, _, v = s.partition("=")
        k = k.removeprefix("policy.")
        try:
            overrides[k] = json.loads(v)
        except json.JSONDecodeError:
            overrides[k] = v
    run(args.task, args.demos, args.steps, args.batch_size, args.seeds, overrides, args.methods, args.sim_episodes, args.open_loop_too,
        args.gamma_noise)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
