"""CNMP against LeRobot's ACT and Diffusion Policy by number of demonstrations, through the stock CLIs.

One cell of the table = (task, method, number of demos N). For each cell this script:

1. trains with stock ``lerobot-train`` on the first N episodes of the task's committed dataset
   (LeRobot's own ``--dataset.episodes=[0,...,N-1]``; a task whose demos are recorded in a structured order
   lists its own ``episode_order``, e.g. cnmp_pickplace's grid corners first: LeRobot's sampler then draws frames of those episodes
   only; the normalization statistics are the dataset's ``meta/stats.json``, i.e. of all its episodes, for
   every method alike: CNMP's in-memory bank computes its statistics over all episodes too, but draws its
   training episodes from the sampler's episode ids), with the method's committed config under ``configs/``;
   it measures the training process's wall time (start-up included) and peak RSS (``os.wait4``'s rusage of
   that process);
2. evaluates with stock ``lerobot-eval`` on fixed seeds (``--seed=100000``, ``--eval.n_episodes`` 50,
   ``--eval.batch_size=10``, no videos: ``--env.render_mode=null``) and reads ``pc_success`` from its
   ``eval_info.json``;
3. times ``select_action`` in this process on the trained checkpoint with its processors, on observations
   of the task's env (one env, seeds 100000..., LeRobot's rollout order: env preprocessor, preprocessor,
   ``select_action``, postprocessor): p50 of ``select_action`` alone and of the whole step. ACT and
   Diffusion predict chunks, so most of their calls pop a queued action; their p95 / max are recorded too;
4. writes ``outputs/compare/<task>/<method>_<N>demos.json``.

``promp`` (``--methods promp``; obstacle2d, conditioned on the episode's SM points, and the tasks with γ, a
contextual ProMP conditioned on γ) has no gradient training: step 1 is ``lerobot-cnmp-fit-promp`` (closed
form, on the same N episodes), which saves it as a LeRobot policy (``--policy.type=promp``); steps 2-4 are
the same as the others'. It runs open loop and is labelled so in its JSON and in the table (``PROMP_LABEL``).

An existing result file with ``"status": "ok"`` is skipped (``--force`` reruns it). A failing training or
evaluation writes the cell's file with ``"status": "error"``, the error and the log's path, and the script
ends with exit status 1 after the other cells (an error cell is rerun on the next call). Nothing is
hard-coded: every figure is read from the CLIs' outputs.

Methods and their configs (no images anywhere: ``observation.state`` + ``observation.environment_state``):

- ``cnmp``: the project's configs (``configs/cnmp_obstacle2d.json``, ``configs/cnmp_metaworld_reach.json``,
  ``configs/cnmp_so101.json``, ``configs/cnmp_pickplace.json``).
- ``act``: ``configs/act_cpu_<task>.json``: LeRobot's ACT shrunk for CPU: dim_model 128, 4 heads,
  dim_feedforward 512, 2 encoder layers, 1 decoder layer, no VAE (``use_vae=false``), no vision backbone
  (none is built without image features), chunk_size = n_action_steps = 20, lr 1e-4, batch 32; 0.67 M
  parameters on obstacle2d (the default ACT has ~40 M).
- ``diffusion``: ``configs/diffusion_cpu_<task>.json``: LeRobot's Diffusion Policy (1-D conv U-Net) with
  down_dims (64, 128), diffusion_step_embed_dim 64, kernel 5, n_obs_steps 2, horizon 16, n_action_steps 8,
  DDIM with 100 training timesteps and 10 inference steps, lr 3e-4 (100 warm-up steps, cosine), batch 32;
  1.11 M parameters on obstacle2d, 1.06 M on MetaWorld (the default down_dims are (512, 1024, 2048)).

MetaWorld and cnmp_pickplace: the dataset stores γ (MetaWorld: the first frame's object and goal positions;
pickplace: the object's position) as ``observation.task_params``,
which ACT and Diffusion do not read (they take ``observation.state``, ``observation.environment_state`` and
images). For them this script derives a copy of the dataset with that column renamed to
``observation.environment_state`` (LeRobot's ``dataset_tools.modify_features``; same values, same
statistics) under ``outputs/compare/datasets/``, and ``lerobot-eval`` gets
``--rename_map={"observation.task_params": "observation.environment_state"}`` (the env's processor names γ
``observation.task_params``, CNMP's name). So every method sees the same inputs.

Training budget rule (``BUDGET_RULE``): the same training wall time for every method, about 120 s of
training loop per cell on this 2-core CPU (one thread), converted once into a fixed number of steps per
method from the throughput measured on cnmp_obstacle2d with 5 demos at 200 steps (shared
machine: CNMP ~100 steps/s at batch 8 × 8 draws; ACT 7.4 steps/s and Diffusion 4.5 steps/s at batch 32,
LeRobot's window loading dominating both), and kept for all tasks and demo counts: ``STEPS``, except where a
task's entry sets its own (``cnmp_so101``'s CNMP is twice as wide, 4500 steps; ``cnmp_pickplace``'s CNMP
keeps its committed config's 4000). CNMP's 9000 is
its committed obstacle2d config. ``--steps METHOD=N`` overrides both; the cell's JSON
records the steps used, the rule, the process wall time and the training loop's own time (``train_loop_s``,
LeRobot's progress bar). This budget is small for ACT and Diffusion (a few thousand samples per demo): the
table says what each method reaches in ~2 min of CPU, not at its plateau.

```bash
python -m bench.compare_policies --tasks cnmp_obstacle2d cnmp_metaworld_reach --methods cnmp act diffusion --demos 5 10
python -m bench.compare_policies --report   # outputs/compare/report.md, docs/compare_policies.png and .md
```
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

from bench.common import REPO, provenance

BIN = Path(sys.executable).parent
OUT = REPO / "outputs" / "compare"
PLOT = REPO / "docs" / "compare_policies.png"
SEED = 100000
BUDGET_S = 120

STEPS = {"cnmp": 9000, "act": 900, "diffusion": 600, "promp": 0}
BUDGET_RULE = (f"same training wall time for every method: ~{BUDGET_S} s of training loop per cell on a 2-core CPU "
               "(1 thread), converted once into fixed steps per method from the throughput measured on "
               "cnmp_obstacle2d with 5 demos (CNMP ~100 steps/s at batch 8 x 8 draws, ACT 7.4 and Diffusion 4.5 "
               f"steps/s at batch 32): {STEPS}; kept for every task and number of demos, except cnmp_so101's CNMP "
               "(256 wide, ~2x the cost per step): 4500, and cnmp_pickplace's CNMP: its committed config's 4000")

METHODS = ("cnmp", "act", "diffusion", "promp")
STOCK = ("cnmp", "act", "diffusion")  # trained by lerobot-train, evaluated by lerobot-eval
PROMP_LABEL = ("open loop: movement_primitives' ProMP (31 RBFs per action dim, lerobot_cnmp.promp.baselines.ProMPBaseline) "
               "fitted in closed form on the first N demos' actions by lerobot-cnmp-fit-promp, saved as a LeRobot "
               "policy (--policy.type=promp) and evaluated by the same lerobot-eval; at each episode's first step "
               "it is conditioned on the episode's conditions (observation.environment_state) or, on a task with "
               "γ, on γ (a contextual ProMP: the weights' Gaussian conditioned on γ), and its mean action "
               "trajectory is commanded on the demos' schedule (step k -> phase k/(T-1), T the demos' median "
               "length, then the last action), whatever the robot senses")
PROMP_BUDGET = "ProMP is fitted in closed form (EM of movement_primitives), no training steps; train_loop_s is the fit"
RENAME_ENV_STATE = {"observation.task_params": "observation.environment_state"}

TASKS = {
    "cnmp_obstacle2d": {
        "dataset": "datasets/cnmp_obstacle2d",
        "env": ["--env.type=cnmp_obstacle2d", "--env.render_mode=null"],
        "configs": {"cnmp": "configs/cnmp_obstacle2d.json", "act": "configs/act_cpu_obstacle2d.json",
                    "diffusion": "configs/diffusion_cpu_obstacle2d.json"},
        "promp": "conditions",  # the episode's conditions are points of the SM: ProMP is conditioned on them
    },
    "cnmp_metaworld_reach": {
        "dataset": "datasets/cnmp_metaworld_reach",
        "env": ["--env.type=cnmp_metaworld", "--env.task=reach-v3"],
        "configs": {"cnmp": "configs/cnmp_metaworld_reach.json", "act": "configs/act_cpu_metaworld_reach.json",
                    "diffusion": "configs/diffusion_cpu_metaworld_reach.json"},
        # ACT / Diffusion read γ as observation.environment_state: a renamed copy (see the docstring)
        "env_state_copy": {"act", "diffusion"},
        # a contextual ProMP over the demos' actions (MetaWorld's hand deltas + gripper), conditioned on γ
        "promp": "task_params",
    },
    "cnmp_metaworld_push": {
        "dataset": "datasets/cnmp_metaworld_push",
        "env": ["--env.type=cnmp_metaworld", "--env.task=push-v3"],
        "configs": {"cnmp": "configs/cnmp_metaworld_push.json", "act": "configs/act_cpu_metaworld_push.json",
                    "diffusion": "configs/diffusion_cpu_metaworld_push.json"},
        "env_state_copy": {"act", "diffusion"},
        "promp": "task_params",
    },
    "cnmp_metaworld_pickplace": {
        "dataset": "datasets/cnmp_metaworld_pickplace",
        "env": ["--env.type=cnmp_metaworld", "--env.task=pick-place-v3"],
        "configs": {"cnmp": "configs/cnmp_metaworld_pickplace.json", "act": "configs/act_cpu_metaworld_pickplace.json",
                    "diffusion": "configs/diffusion_cpu_metaworld_pickplace.json"},
        "env_state_copy": {"act", "diffusion"},
        "promp": "task_params",
    },
    "cnmp_so101": {  # the third-party SO-101 pick and place (extra so101); γ is its own environment_state
        "dataset": "datasets/cnmp_so101",
        "env": ["--env.type=cnmp_so101", "--env.render_mode=null"],
        "configs": {"cnmp": "configs/cnmp_so101.json", "act": "configs/act_cpu_so101.json",
                    "diffusion": "configs/diffusion_cpu_so101.json"},
        # its CNMP is 256 wide (3 x 256 encoder and decoder): a step costs ~2x the 128-wide one's, so half the
        # steps keep the ~2 min budget (the cell's train_loop_s records what it took)
        "steps": {"cnmp": 4500},
    },
    "cnmp_pickplace": {  # the paper's Sec. IV-B: γ = the object's position, 8 demos on a 2 x 4 grid of γ
        "dataset": "datasets/cnmp_pickplace",
        "env": ["--env.type=cnmp_pickplace", "--env.render_mode=null"],
        "configs": {"cnmp": "configs/cnmp_pickplace.json", "act": "configs/act_cpu_pickplace.json",
                    "diffusion": "configs/diffusion_cpu_pickplace.json"},
        "env_state_copy": {"act", "diffusion"},
        "steps": {"cnmp": 4000},  # its committed config's steps (fewer than the 9000 of the budget)
        # the grid's four corners first, then the four inner points: N = 5 covers the grid's extent
        "episode_order": [0, 7, 3, 4, 1, 6, 2, 5],
        "promp": "task_params",  # a contextual ProMP: its weights conditioned on the episode's γ
    },
    # sensorimotor classification (paper Sec. IV-D): CNMP with feedback vs ProMP open loop; no ACT / Diffusion
    "cnmp_weights": {
        "dataset": "datasets/cnmp_weights",
        "env": ["--env.type=cnmp_weights", "--env.render_mode=null"],
        "configs": {"cnmp": "configs/cnmp_weights.json"},
        # no conditions, no γ: the class is only in the sensed F/T, which an open-loop plan never reads
        "promp": "none",
        "no_cells": {m: "its observation is observation.state alone (the class is in the sensed F/T, no γ), and "
                        "LeRobot 0.6.1's ACT and Diffusion refuse that ('You must provide at least one image or "
                        "the environment state among the inputs.', their validate_features)"
                     for m in ("act", "diffusion")},
    },
}


def episodes(task: str, n: int) -> list[int]:
    """The dataset episodes of a task's N-demo cell: the first N of its ``episode_order`` (default 0..N-1)."""
    order = TASKS[task].get("episode_order")
    return list(range(n)) if order is None else list(order[:n])


class CellError(RuntimeError):
    """A training, evaluation or measurement of one cell failed."""


def result_path(out: Path, task: str, method: str, n: int) -> Path:
    return out / task / f"{method}_{n}demos.json"


def should_run(path: Path, force: bool) -> bool:
    """A cell runs unless its result file exists with status ok (``force`` reruns it anyway). An unreadable
    file or an error cell runs again."""
    if force or not path.is_file():
        return True
    try:
        return json.loads(path.read_text()).get("status") != "ok"
    except (OSError, ValueError):
        return True


def env_state_copy(task: str, out: Path) -> Path:
    """The task's dataset with ``observation.task_params`` renamed to ``observation.environment_state``
    (same values and statistics), made once under ``out/datasets/``."""
    import numpy as np
    from lerobot.datasets.dataset_tools import modify_features
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    src_root = REPO / TASKS[task]["dataset"]
    dst = out / "datasets" / f"{Path(src_root).name}_envstate"
    source = dataset_fingerprint(src_root)
    made_from = dst / "made_from.json"
    if (dst / "meta" / "stats.json").is_file() and made_from.is_file():
        stats = json.loads((dst / "meta" / "stats.json").read_text())
        if "observation.environment_state" in stats and json.loads(made_from.read_text()) == source:
            return dst
    import shutil

    shutil.rmtree(dst, ignore_errors=True)
    src = LeRobotDataset(f"lerobot-cnmp/{src_root.name}", root=src_root)
    key = "observation.task_params"
    values = np.stack([np.asarray(x, dtype=np.float32) for x in src.hf_dataset.with_format("numpy")[key]])
    modify_features(src, add_features={"observation.environment_state": (values, dict(src.meta.features[key]))},
                    remove_features=[key], output_dir=dst, repo_id=f"lerobot-cnmp/{dst.name}")
    # modify_features writes no statistics for an added feature: the values are the same, so are the stats
    stats_file = dst / "meta" / "stats.json"
    stats = json.loads(stats_file.read_text())
    src_stats = json.loads((src_root / "meta" / "stats.json").read_text())
    stats["observation.environment_state"] = src_stats[key]
    stats.pop(key, None)
    stats_file.write_text(json.dumps(stats, indent=4))
    made_from.write_text(json.dumps(source, indent=2))  # last: a copy cut short is remade on the next call
    return dst


def dataset_fingerprint(root: Path) -> dict:
    """sha256 of a dataset's data and meta files: the renamed copy is remade when its source changes (a
    re-recorded dataset must not be trained on through a stale copy)."""
    import hashlib

    files = sorted(p for p in Path(root).rglob("*") if p.is_file() and p.suffix in (".parquet", ".json"))
    if not files:
        raise CellError(f"{root} holds no dataset (no parquet or json files)")
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


def run_logged(cmd: list[str], log: Path, env: dict) -> dict:
    """Run ``cmd`` with stdout and stderr to ``log``; its wall time, exit status and peak RSS (MB, from
    ``os.wait4``: that process and the children it waited for)."""
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        f.write("$ " + shlex.join(cmd) + "\n")
        f.flush()
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=env, cwd=REPO)
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return {"rc": proc.returncode, "wall_s": round(time.perf_counter() - t0, 2),
            "peak_rss_mb": round(usage.ru_maxrss / 1024, 1)}


def log_tail(log: Path, n: int = 15) -> str:
    """The last ``n`` lines of a log that are not progress bars."""
    lines = [x for x in log.read_text(errors="replace").replace("\r", "\n").splitlines()
             if x.strip() and "it/s]" not in x and "step/s]" not in x and "s/it]" not in x]
    return "\n".join(lines[-n:])


def train_loop_s(log: Path) -> float | None:
    """The training loop's own time (LeRobot's progress bar at 100 %: start-up and saving excluded), or
    None when the log has no finished bar."""
    import re

    if not Path(log).is_file():
        return None
    found = re.findall(r"Training: 100%\|[^\[]*\[(?:(\d+):)?(\d+):(\d+)<", Path(log).read_text(errors="replace"))
    if not found:
        return None
    h, m, sec = found[-1]
    return float(int(h or 0) * 3600 + int(m) * 60 + int(sec))


def child_env() -> dict:
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")
    env.setdefault("HF_HUB_OFFLINE", "1")
    env.setdefault("MUJOCO_GL", "egl")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    return env


def train_command(task: str, method: str, n: int, steps: int, out_dir: Path, dataset_root: Path | None) -> list[str]:
    cmd = [str(BIN / "lerobot-train"), f"--config_path={TASKS[task]['configs'][method]}", "--policy.device=cpu",
           f"--dataset.episodes=[{','.join(str(i) for i in episodes(task, n))}]", f"--steps={steps}", f"--save_freq={steps}",
           f"--job_name={task}_{method}_{n}demos", f"--output_dir={out_dir}"]
    if dataset_root is not None:
        cmd.insert(2, f"--dataset.root={dataset_root.relative_to(REPO) if REPO in dataset_root.parents else dataset_root}")
    return cmd


def fit_command(task: str, n: int, out_dir: Path) -> list[str]:
    """ProMP's "training": ``lerobot-cnmp-fit-promp`` on the cell's episodes (closed form, see PROMP_LABEL)."""
    return [str(BIN / "lerobot-cnmp-fit-promp"), f"--dataset_root={REPO / TASKS[task]['dataset']}",
            "--episodes=" + ",".join(map(str, episodes(task, n))), f"--conditioning={TASKS[task]['promp']}",
            f"--output_dir={out_dir}"]


def eval_command(task: str, method: str, ckpt: Path, n_episodes: int, batch_size: int, out_dir: Path) -> list[str]:
    cmd = [str(BIN / "lerobot-eval"), f"--policy.path={ckpt}", *TASKS[task]["env"], f"--eval.n_episodes={n_episodes}",
           f"--eval.batch_size={batch_size}", "--policy.device=cpu", f"--seed={SEED}", f"--output_dir={out_dir}"]
    if method in TASKS[task].get("env_state_copy", ()):
        cmd.append("--rename_map=" + json.dumps(RENAME_ENV_STATE))
    return cmd


def env_config(task: str):
    """The task's EnvConfig built from the same ``--env.*`` arguments that lerobot-eval gets (``type`` picks
    the registered class, the others are string fields or ``null``)."""
    from lerobot.envs.configs import EnvConfig

    import lerobot_cnmp.sims  # noqa: F401  (registers the env types)

    kw = dict(a.removeprefix("--env.").split("=", 1) for a in TASKS[task]["env"])
    cls = EnvConfig.get_choice_class(kw.pop("type"))
    return cls(**{k: (None if v == "null" else v) for k, v in kw.items()})


def measure_latency(task: str, method: str, ckpt: Path, n_calls: int = 600) -> dict:
    """p50 / p95 / max (ms) of ``select_action`` alone and of preprocessor + select_action + postprocessor on
    one env of the task, LeRobot's rollout order, episodes seeded from ``SEED``, ``n_calls`` steps."""
    import numpy as np
    import torch
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.envs.factory import make_env, make_env_pre_post_processors
    from lerobot.envs.utils import preprocess_observation
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    torch.set_num_threads(1)
    env_cfg = env_config(task)
    cfg = PreTrainedConfig.from_pretrained(ckpt)
    cfg.pretrained_path = Path(ckpt)
    cfg.device = "cpu"
    rename = RENAME_ENV_STATE if method in TASKS[task].get("env_state_copy", ()) else {}
    policy = make_policy(cfg=cfg, env_cfg=env_cfg, rename_map=rename)
    policy.eval()
    pre, post = make_pre_post_processors(policy_cfg=cfg, pretrained_path=ckpt, preprocessor_overrides={
        "device_processor": {"device": "cpu"}, "rename_observations_processor": {"rename_map": rename}})
    env_pre, env_post = make_env_pre_post_processors(env_cfg=env_cfg, policy_cfg=cfg)
    env = next(iter(make_env(env_cfg, n_envs=1, use_async_envs=False)[env_cfg.type].values()))
    sel, whole = [], []
    seed = SEED
    try:
        obs, _ = env.reset(seed=[seed])
        policy.reset()
        while len(sel) < n_calls:
            t0 = time.perf_counter()
            batch = preprocess_observation(obs)
            batch["task"] = [""]
            batch = pre(env_pre(batch))
            t1 = time.perf_counter()
            with torch.inference_mode():
                action = policy.select_action(batch)
            t2 = time.perf_counter()
            action = env_post({"action": post(action)})["action"]
            t3 = time.perf_counter()
            sel.append(t2 - t1)
            whole.append(t3 - t0)
            obs, _, term, trunc, _ = env.step(action.to("cpu").numpy())
            if term[0] or trunc[0]:
                seed += 1
                obs, _ = env.reset(seed=[seed])
                policy.reset()
    finally:
        env.close()

    def q(x, p):
        return round(float(np.percentile(np.asarray(x) * 1e3, p)), 4)

    return {"select_action_p50_ms": q(sel, 50), "select_action_p95_ms": q(sel, 95),
            "select_action_max_ms": round(max(sel) * 1e3, 4), "step_with_processors_p50_ms": q(whole, 50),
            "latency_calls": n_calls, "latency_episode_seeds": list(range(SEED, seed + 1))}


def run_cell(task: str, method: str, n: int, *, out: Path, steps: int, n_episodes: int, batch_size: int) -> dict:
    """Train, evaluate and time one cell; return its result record (raises CellError on a failure)."""
    promp = method == "promp"
    if promp and not TASKS[task].get("promp"):
        raise CellError(f"ProMP is not set up for {task}: its episodes carry neither SM-point conditions nor γ "
                        "to condition on")
    if method in TASKS[task].get("no_cells", {}):
        raise CellError(f"{method} has no cell on {task}: {TASKS[task]['no_cells'][method]}")
    cell_dir = out / task / f"{method}_{n}demos"
    train_dir, eval_dir = cell_dir / "train", cell_dir / "eval"
    import shutil

    shutil.rmtree(cell_dir, ignore_errors=True)  # lerobot-train refuses an existing output dir
    dataset_root = env_state_copy(task, out) if method in TASKS[task].get("env_state_copy", ()) else None
    n_total = json.loads((REPO / TASKS[task]["dataset"] / "meta" / "info.json").read_text())["total_episodes"]
    if n > n_total:
        raise CellError(f"{task} has {n_total} demos, {n} asked")
    rec = {"task": task, "method": method, "n_demos": n, "episodes": episodes(task, n), "steps": 0 if promp else steps,
           "budget_rule": PROMP_BUDGET if promp else BUDGET_RULE, "date": dt.datetime.now().isoformat(timespec="seconds"),
           "config": None if promp else TASKS[task]["configs"][method], "host_cpus": os.cpu_count()}
    if promp:
        rec["label"] = PROMP_LABEL
    env = child_env()

    cmd = fit_command(task, n, train_dir) if promp else train_command(task, method, n, steps, train_dir, dataset_root)
    tool = "lerobot-cnmp-fit-promp" if promp else "lerobot-train"
    rec["train_command"] = shlex.join(cmd)
    rec["train_log"] = str(cell_dir / "train.log")
    r = run_logged(cmd, cell_dir / "train.log", env)
    rec.update(train_wall_s=r["wall_s"], train_loop_s=train_loop_s(cell_dir / "train.log"),
               train_peak_rss_mb=r["peak_rss_mb"])
    ckpt = train_dir / "pretrained_model" if promp else train_dir / "checkpoints" / "last" / "pretrained_model"
    if r["rc"] != 0 or not (ckpt / "config.json").is_file():
        raise CellError(f"{tool} failed (exit {r['rc']}), log {cell_dir / 'train.log'}:\n"
                        f"{log_tail(cell_dir / 'train.log')}", rec)
    rec["checkpoint"] = provenance(ckpt)
    if promp:
        rec["train_loop_s"] = json.loads((train_dir / "fit_info.json").read_text())["fit_s"]  # the fit alone
    elif rec["checkpoint"]["step"] != steps:
        raise CellError(f"the checkpoint is at step {rec['checkpoint']['step']}, not {steps}", rec)

    cmd = eval_command(task, method, ckpt, n_episodes, batch_size, eval_dir)
    rec["eval_command"] = shlex.join(cmd)
    rec["eval_log"] = str(cell_dir / "eval.log")
    r = run_logged(cmd, cell_dir / "eval.log", env)
    rec.update(eval_wall_s=r["wall_s"], eval_peak_rss_mb=r["peak_rss_mb"])
    info_file = eval_dir / "eval_info.json"
    if r["rc"] != 0 or not info_file.is_file():
        raise CellError(f"lerobot-eval failed (exit {r['rc']}), log {cell_dir / 'eval.log'}:\n"
                        f"{log_tail(cell_dir / 'eval.log')}", rec)
    info = json.loads(info_file.read_text())
    overall = info["overall"]
    if overall.get("n_episodes") != n_episodes:
        raise CellError(f"eval_info.json has {overall.get('n_episodes')} episodes, {n_episodes} asked", rec)
    rec.update(pc_success=float(overall["pc_success"]), n_episodes=int(overall["n_episodes"]),
               avg_sum_reward=overall.get("avg_sum_reward"), eval_info=str(info_file))
    # lerobot-eval seeds batch b's env i with seed + b * batch_size + i: episode k has seed + k
    rec["seeds"] = list(range(SEED, SEED + n_episodes))

    rec.update(measure_latency(task, method, ckpt))
    rec["status"] = "ok"
    return rec




def run(args) -> int:
    steps, explicit = dict(STEPS), set()  # --steps overrides a task's own steps too
    for s in args.steps or []:
        m, _, v = s.partition("=")
        if m not in METHODS or not v.isdigit():
            raise SystemExit(f"--steps takes METHOD=N with METHOD in {METHODS}, got {s!r}")
        steps[m] = int(v)
        explicit.add(m)
    failed = []
    for task in args.tasks:
        for n in args.demos:
            for method in args.methods:
                path = result_path(args.out, task, method, n)
                if method in TASKS[task].get("no_cells", {}):
                    print(f"skip {task} {method}: no cell, {TASKS[task]['no_cells'][method]}", flush=True)
                    continue
                if not should_run(path, args.force):
                    print(f"skip {task} {method} {n} demos: {path} exists (--force reruns it)", flush=True)
                    continue
                n_steps = steps[method] if method in explicit else TASKS[task].get("steps", {}).get(method, steps[method])
                print(f"run  {task} {method} {n} demos ({n_steps} steps)", flush=True)
                t0 = time.perf_counter()
                try:
                    rec = run_cell(task, method, n, out=args.out, steps=n_steps, n_episodes=args.n_episodes,
                                   batch_size=args.batch_size)
                except (Exception, SystemExit) as e:  # noqa: BLE001 - recorded in the cell's file; the run ends non-zero
                    partial = e.args[1] if isinstance(e, CellError) and len(e.args) > 1 else {}
                    rec = {**partial, "task": task, "method": method, "n_demos": n, "status": "error",
                           "error": f"{type(e).__name__}: {e.args[0] if e.args else e}"}
                    failed.append(path)
                rec["cell_wall_s"] = round(time.perf_counter() - t0, 1)
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(json.dumps(rec, indent=2))
                print(f"     -> {rec['status']}: pc_success {rec.get('pc_success')} train {rec.get('train_wall_s')} s, "
                      f"{path}", flush=True)
                if rec["status"] != "ok":
                    print(rec["error"][-2000:], file=sys.stderr, flush=True)
    if failed:
        print(f"{len(failed)} cell(s) failed: " + ", ".join(map(str, failed)), file=sys.stderr)
        return 1
    return 0


def load_results(out: Path) -> list[dict]:
    recs = []
    for f in sorted(out.glob("*/*_*demos.json")):
        rec = json.loads(f.read_text())
        if rec.get("train_log") and rec.get("train_loop_s") is None:
            rec["train_loop_s"] = train_loop_s(rec["train_log"])
        rec["_file"] = str(f)
        recs.append(rec)
    return recs


def report_table(recs: list[dict]) -> str:
    """A markdown table of all result records (error cells shown as such)."""
    order = {m: i for i, m in enumerate(METHODS)}
    tasks = {t: i for i, t in enumerate(TASKS)}
    rows = sorted(recs, key=lambda r: (tasks.get(r["task"], 99), r["task"], r["n_demos"], order.get(r["method"], 99),
                                       r["method"]))
    lines = ["| task | method | demos | pc_success | episodes | steps | train wall (s) | train loop (s) | train peak RSS (MB) "
             "| select_action p50 / p95 (ms) | step with processors p50 (ms) | date |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]

    def f(v, nd=1):
        return "" if v is None else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))

    for r in rows:
        if r.get("status") != "ok":
            err = str(r.get("error", "no status")).splitlines()[0][:120].replace("|", "\\|")
            lines.append(f"| {r['task']} | {r['method']} | {r['n_demos']} | **error**: {err} | | | | | | | | "
                         f"{r.get('date', '')} |")
            continue
        method = r["method"] + (" (open loop†)" if r.get("label") else "")
        sel = "" if r.get("select_action_p50_ms") is None else \
            f"{f(r['select_action_p50_ms'], 3)} / {f(r.get('select_action_p95_ms'), 2)}"
        lines.append(f"| {r['task']} | {method} | {r['n_demos']} | {f(r['pc_success'])} | {r['n_episodes']} | "
                     f"{r['steps']} | {f(r['train_wall_s'])} | {f(r.get('train_loop_s'), 0)} | {f(r['train_peak_rss_mb'], 0)} | "
                     f"{sel} | {f(r.get('step_with_processors_p50_ms'), 3)} | "
                     f"{r.get('date', '')[:10]} |")
    labels = sorted({r["label"] for r in rows if r.get("status") == "ok" and r.get("label")})
    if any(r.get("method") in ("act", "diffusion") for r in rows):
        lines.append("\nACT and Diffusion predict action chunks: most select_action calls pop a queued action "
                     "(p50); the p95 includes the calls that run the network.")
    lines += [f"\n† {text}" for text in labels]
    return "\n".join(lines)


def summary_table(recs: list[dict]) -> str:
    """One row per task and number of demos, one column per method: pc_success (training loop seconds);
    "err" for a failed cell, "–" for a cell not run."""
    cells = [r for r in recs if "n_demos" in r and "task" in r]  # ok and error cells
    methods = [m for m in METHODS if any(r["method"] == m for r in cells)]
    tasks = {t: i for i, t in enumerate(TASKS)}
    keys = sorted({(r["task"], r["n_demos"]) for r in cells}, key=lambda k: (tasks.get(k[0], 99), k[0], k[1]))
    cell = {(r["task"], r["n_demos"], r["method"]): r for r in cells}
    lines = ["| task | demos | " + " | ".join(m + (" (open loop)" if m == "promp" else "") for m in methods) + " |",
             "|---|---:|" + "---:|" * len(methods)]
    for task, n in keys:
        vals = []
        for m in methods:
            r = cell.get((task, n, m))
            if r is None:
                vals.append("–")
            elif r.get("status") != "ok":
                vals.append("err")
            else:
                loop = r.get("train_loop_s") if r.get("train_loop_s") is not None else r.get("train_wall_s")
                vals.append(f"{r['pc_success']:.0f}" + ("" if loop is None else f" ({loop:.0f} s)"))
        lines.append(f"| {task} | {n} | " + " | ".join(vals) + " |")
    return "\n".join(lines)


def report_plot(recs: list[dict], path: Path) -> Path:
    """Success vs number of demos, one line per method, one panel per task (ok cells only)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in recs if r.get("status") == "ok"]
    order = {t: i for i, t in enumerate(TASKS)}
    tasks = sorted({r["task"] for r in recs}, key=lambda t: (order.get(t, 99), t))
    if not tasks:
        raise ValueError("no result files to plot")
    ncol = min(4, len(tasks))
    nrow = -(-len(tasks) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.4 * ncol, 3.6 * nrow + 0.6), squeeze=False)
    panels = list(axes.flat)
    for ax in panels[len(tasks):]:
        ax.set_visible(False)
    methods = [m for m in METHODS if any(r["method"] == m for r in ok)] + sorted({r["method"] for r in ok} - set(METHODS))
    color = {m: f"C{i}" for i, m in enumerate(methods)}  # one colour per method in every panel
    for ax, task in zip(panels, tasks):
        for method in methods:
            pts = sorted((r["n_demos"], r["pc_success"]) for r in ok if r["task"] == task and r["method"] == method)
            if pts:
                open_loop = any(r.get("label") for r in ok if r["method"] == method)
                ax.plot(*zip(*pts, strict=True), marker="o", label=method + (" (open loop)" if open_loop else ""),
                        linestyle=":" if open_loop else "-", color=color[method])
        ax.set_title(task)
        ax.set_xlabel("demonstrations")
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
        ns = sorted({r["n_demos"] for r in recs if r["task"] == task})
        ax.set_xticks(ns)
    for row in axes:
        row[0].set_ylabel("pc_success (%)")
    handles = {}
    for ax in panels:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(lab, h)
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=len(handles), frameon=False)
    fig.suptitle("success vs demonstrations (50 episodes, seeds 100000..; equal training wall time per cell)",
                 fontsize=10)
    fig.tight_layout(rect=(0, 0.6 / (3.6 * nrow + 0.6), 1, 1))
    from lerobot_cnmp.plot import save_figure

    return save_figure(fig, path, dpi=120)


def report(out: Path, plot: Path) -> str:
    recs = load_results(out)
    if not recs:
        raise SystemExit(f"no result files under {out}")
    table = report_table(recs)
    text = (f"# Policy comparison\n\nBudget rule: {recs[0].get('budget_rule', BUDGET_RULE)}\n\n"
            f"pc_success (training loop s):\n\n{summary_table(recs)}\n\nEvery cell:\n\n{table}\n\n"
            f"Seeds: lerobot-eval --seed={SEED}; commands in each cell's JSON under "
            f"{out.resolve().relative_to(REPO) if out.resolve().is_relative_to(REPO) else out}.\n")
    (out / "report.md").write_text(text)
    plot.with_suffix(".md").parent.mkdir(parents=True, exist_ok=True)
    plot.with_suffix(".md").write_text(text)  # beside the plot (docs/compare_policies.md), committed with it
    report_plot(recs, plot)
    return text


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS))
    p.add_argument("--methods", nargs="+", default=list(STOCK), choices=list(METHODS),
                   help="promp: the open-loop ProMP policy (see PROMP_LABEL), where the task's conditions or γ allow it")
    p.add_argument("--demos", nargs="+", type=int, default=[5, 10])
    p.add_argument("--n_episodes", type=int, default=50)
    p.add_argument("--batch_size", type=int, default=10, help="lerobot-eval --eval.batch_size")
    p.add_argument("--steps", action="append", help=f"METHOD=N: override the budget's steps {STEPS} (recorded)")
    p.add_argument("--force", action="store_true", help="rerun cells whose result file exists")
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--report", action="store_true", help="only build the table and the plot from the result files")
    p.add_argument("--plot", type=Path, default=PLOT)
    args = p.parse_args(argv)
    if args.report:
        print(report(args.out, args.plot))
        return 0
    return run(args)


if __name__ == "__main__":
    raise SystemExit(main())
