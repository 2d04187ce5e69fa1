"""The cells of the policy comparison: tasks, methods, their configs, the time marks and the commands.

A cell is (task, method, number of demos N); it is trained once per training seed. Everything a cell runs is a
stock CLI: ``lerobot-train`` (``lerobot-cnmp-fit-promp`` for ProMP) and ``lerobot-eval``; this module builds
their command lines and the time schedule, :mod:`bench.compare_run` runs them, :mod:`bench.compare_report`
reads the results.

Time marks to steps (:func:`schedule`): ``lerobot-train`` saves by step, so a method's training-loop rate
(steps/s, measured on this machine by a short probe run of the same cell, :func:`bench.compare_run.step_rate`)
turns the marks (``MARKS_S``, those below the method's cap, and the cap) into steps. The run is ONE
``lerobot-train`` with ``--steps`` = the cap's steps and ``--save_freq`` = the steps of the marks' greatest common
divisor, so every mark is a multiple of it; checkpoints between marks are deleted as soon as a later one exists.
Why not a long run stopped at the cap, keeping the checkpoints nearest each mark: the learning-rate schedules
(Diffusion's cosine, CNMP's decay) are set from ``--steps``, so a run cut at the cap would never anneal; here
each method's schedule spans its cap, as it would in a run of that length. The curve's x is the training loop's
measured time at each checkpoint (LeRobot's progress bar), not the nominal mark: a machine that slows down moves
the points, it does not mislabel them.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from bench.common import REPO

BIN = Path(sys.executable).parent
SEED = 100000  # the held-out evaluation: --seed=100000, 50 episodes (the best checkpoint of each curve)
CURVE_SEED = 200000  # the curve's evaluations: 20 episodes per checkpoint, seeds disjoint from the held-out ones
CURVE_EPISODES = 20
HELDOUT_EPISODES = 50

METHODS = ("cnmp", "act", "diffusion", "promp", "cnmp_noterm", "cnmp_term", "cnmp_nofb")
STOCK = ("cnmp", "act", "diffusion")  # trained by lerobot-train, evaluated by lerobot-eval
# ablations: a method's config with extra lerobot-train arguments, a cell of its own (not run unless named)
VARIANTS = {"cnmp_noterm": ("cnmp", ["--policy.linear_task_term=false"]),  # CNMP without the linear γ term
            "cnmp_term": ("cnmp", ["--policy.linear_task_term=true"]),  # with it where a config pins it off
            # the paper's whole-demo draws only, where a config (SO-101's) trains mostly on execution-shaped ones
            "cnmp_nofb": ("cnmp", ["--policy.sampling.feedback_draw_weight=0"])}
MARKS_S = (30, 60, 120, 300, 600, 1200, 1800)  # training-loop seconds at which a checkpoint is kept
# training-loop cap per method (s): CNMP's curves flatten within a few minutes, ACT / Diffusion get 30 min
CAP_S = {"cnmp": 600, "act": 1800, "diffusion": 1800}
# training seeds per method: CNMP is cheap (3); ACT / Diffusion cost 30 min a seed (1); ProMP's fit is closed
# form and deterministic on the fixed N episodes (no seed enters it), so a second seed would repeat the first
N_SEEDS = {"cnmp": 3, "act": 1, "diffusion": 1, "promp": 1}
# methods whose LeRobot preset has no learning-rate schedule (ACT: get_scheduler_preset() is None): a run the
# probe under-counted is extended to the cap by resuming with more steps, the same run as a longer one
CONSTANT_LR = {"act"}
EXTEND_BELOW = 0.85  # ... when it used less than this share of its cap
FIRST_SEED = 1000  # the committed configs' seed; seed i of a cell is FIRST_SEED + i
PROBE_STEPS = {"cnmp": 3000, "act": 250, "diffusion": 150}  # the rate probe's first try (~40 s on one CPU core)
for _variant, (_base, _) in VARIANTS.items():  # a variant trains, and is capped and seeded, as its base method
    for _table in (CAP_S, N_SEEDS, PROBE_STEPS):
        _table.setdefault(_variant, _table[_base])
PROBE_MIN_LOOP_S = 30  # a shorter probe is redone longer: its rate is taken after the warm-up (compare_run.steady_rate)
PROMP_NOTE = ("ProMP: fitted in closed form (EM of movement_primitives) on the fixed first N episodes, deterministic: no "
              "training seed enters the fit: one fit per cell, its curve one point (the fit's seconds), its "
              "spread over seeds 0 by construction, not measured")

PROMP_LABEL = ("open loop: movement_primitives' ProMP (31 RBFs per action dim, lerobot_cnmp.promp.baselines.ProMPBaseline) "
               "fitted in closed form on the first N demos' actions by lerobot-cnmp-fit-promp, saved as a LeRobot "
               "policy (--policy.type=promp) and evaluated by the same lerobot-eval; at each episode's first step "
               "it is conditioned on the episode's conditions (observation.environment_state) or, on a task with "
               "γ, on γ (a contextual ProMP: the weights' Gaussian conditioned on γ; on SO-101 γ is the env's "
               "observation.environment_state, its block and goal positions), and its mean action "
               "trajectory is commanded on the demos' schedule (step k -> phase k/(T-1), T the demos' median "
               "length, then the last action), whatever the robot senses")
RENAME_ENV_STATE = {"observation.task_params": "observation.environment_state"}

# the MetaWorld v3 tasks of the comparison and their short names (dataset datasets/cnmp_metaworld_<name>, configs
# configs/<method>_metaworld_<name>.json, which differ from push's only in the dataset: tests/test_compare_policies.py)
METAWORLD_TASKS = {"reach-v3": "reach", "push-v3": "push", "pick-place-v3": "pickplace",
                   "coffee-push-v3": "coffeepush", "sweep-v3": "sweep"}


def metaworld_cell(task: str, name: str) -> dict:
    """A MetaWorld task's entry: our wrapper env, γ = object and goal positions (observation.task_params), which
    ACT / Diffusion read from a renamed copy as observation.environment_state, and a contextual ProMP on γ."""
    return {"dataset": f"datasets/cnmp_metaworld_{name}", "env": ["--env.type=cnmp_metaworld", f"--env.task={task}"],
            "configs": {"cnmp": f"configs/cnmp_metaworld_{name}.json", "act": f"configs/act_cpu_metaworld_{name}.json",
                        "diffusion": f"configs/diffusion_cpu_metaworld_{name}.json"},
            "env_state_copy": {"act", "diffusion"}, "promp": "task_params"}


CAMERAS = ["corner3", "behindGripper"]  # the camera cells' views (128 x 128): the table with the goal, the gripper's
SO101_CAMERA = "table"  # SO-101's camera cell: one 128 x 128 view over the workspace (lerobot_cnmp.sims.so101.task)


def metaworld_camera_cell(task: str, name: str) -> dict:
    """A MetaWorld task seen by cameras (issue: no privileged positions): its dataset recorded with ``--cameras``
    (γ only as ground truth), every method reading ``observation.state`` and the images; no ProMP (no image path)."""
    return {"dataset": f"datasets/cnmp_metaworld_{name}_cam",
            "env": ["--env.type=cnmp_metaworld", f"--env.task={task}", f"--env.cameras=[{','.join(CAMERAS)}]"],
            "configs": {m: f"configs/{m}{'' if m == 'cnmp' else '_cpu'}_metaworld_{name}_cam.json"
                        for m in ("cnmp", "act", "diffusion")},
            "record": (f"lerobot-cnmp-record --sim cnmp_metaworld --conditions {task} --root datasets/cnmp_metaworld_"
                       f"{name}_cam --n_episodes 50 --max_failed 30 --cameras {' '.join(CAMERAS)}"),
            "no_cells": {"promp": "the contextual ProMP conditions on γ, which the camera cells do not give"}}


TASKS = {
    "cnmp_obstacle2d": {
        "dataset": "datasets/cnmp_obstacle2d",
        "env": ["--env.type=cnmp_obstacle2d", "--env.render_mode=null"],
        "configs": {"cnmp": "configs/cnmp_obstacle2d.json", "act": "configs/act_cpu_obstacle2d.json",
                    "diffusion": "configs/diffusion_cpu_obstacle2d.json"},
        "promp": "conditions",  # the episode's conditions are points of the SM: ProMP is conditioned on them
    },
    # MetaWorld: one entry per task, made by the same rule (metaworld_cell); configs identical but for the dataset
    **{f"cnmp_metaworld_{name}": metaworld_cell(task, name) for task, name in METAWORLD_TASKS.items()},
    **{f"cnmp_metaworld_{name}_cam": metaworld_camera_cell(task, name)
       for task, name in (("push-v3", "push"), ("pick-place-v3", "pickplace"))},
    "cnmp_so101": {  # the third-party SO-101 pick and place (extra so101); γ is its own environment_state
        "dataset": "datasets/cnmp_so101",
        "env": ["--env.type=cnmp_so101", "--env.render_mode=null"],
        "configs": {"cnmp": "configs/cnmp_so101.json", "act": "configs/act_cpu_so101.json",
                    "diffusion": "configs/diffusion_cpu_so101.json"},
        "promp": "environment_state",  # a contextual ProMP on γ, here the env's block and goal positions
    },
    "cnmp_so101_cam": {  # the same task seen by one camera over the table: no block or goal positions
        "dataset": "datasets/cnmp_so101_cam",
        "env": ["--env.type=cnmp_so101", "--env.render_mode=null", f"--env.cameras=[{SO101_CAMERA}]"],
        "configs": {m: f"configs/{m}{'' if m == 'cnmp' else '_cpu'}_so101_cam.json" for m in ("cnmp", "act", "diffusion")},
        "record": (f"lerobot-cnmp-record --sim cnmp_so101 --root datasets/cnmp_so101_cam --overwrite --n_episodes 400 "
                   f"--action_noise 0.1,0.1,0,0 --max_failed 100 --cameras {SO101_CAMERA}"),
        "no_cells": {"promp": "the contextual ProMP conditions on γ, which the camera cells do not give"},
    },
    "cnmp_pickplace": {  # the paper's Sec. IV-B: γ = the object's position, 8 demos on a 2 x 4 grid of γ
        "dataset": "datasets/cnmp_pickplace",
        "env": ["--env.type=cnmp_pickplace", "--env.render_mode=null"],
        "configs": {"cnmp": "configs/cnmp_pickplace.json", "act": "configs/act_cpu_pickplace.json",
                    "diffusion": "configs/diffusion_cpu_pickplace.json"},
        "env_state_copy": {"act", "diffusion"},
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


def seeds_for(method: str, given: list[int] | None, n_seeds: dict) -> list[int]:
    """The training seeds of a method's cells: ``given`` (``--seeds``) for every method but ProMP (one fit,
    see PROMP_NOTE), else ``n_seeds[method]`` seeds from FIRST_SEED."""
    if method == "promp":
        return [given[0] if given else FIRST_SEED]
    return list(given) if given else [FIRST_SEED + i for i in range(n_seeds[method])]


def schedule(rate: float, cap_s: int, marks=MARKS_S) -> dict:
    """``--steps``, ``--save_freq`` and the step of each mark for a run of ``cap_s`` training-loop seconds at
    ``rate`` steps/s: the marks below the cap and the cap, all multiples of ``save_freq`` (the steps of their
    greatest common divisor in seconds)."""
    if rate <= 0 or cap_s <= 0:
        raise ValueError(f"a schedule needs a positive rate and cap, got {rate} steps/s and {cap_s} s")
    kept = sorted({int(m) for m in marks if 0 < m < cap_s} | {int(cap_s)})
    g = math.gcd(*kept)
    save_freq = max(1, round(g * rate))
    return {"rate_steps_per_s": rate, "cap_s": int(cap_s), "steps": save_freq * kept[-1] // g, "save_freq": save_freq,
            "marks": {str(m): save_freq * m // g for m in kept}}


def cell_dir(out: Path, task: str, method: str, n: int) -> Path:
    return out / task / f"{method}_{n}demos"


def record_path(out: Path, task: str, method: str, n: int, seed: int) -> Path:
    """One training seed's record: its schedule, training attempts, curve points and held-out evaluation."""
    return cell_dir(out, task, method, n) / f"seed{seed}.json"


def _dataset_arg(dataset_root: Path | None) -> list[str]:
    if dataset_root is None:
        return []
    return [f"--dataset.root={dataset_root.relative_to(REPO) if REPO in dataset_root.parents else dataset_root}"]


def base_method(method: str) -> str:
    """The method whose config a variant (``VARIANTS``) trains with; a method is its own base."""
    return VARIANTS[method][0] if method in VARIANTS else method


def config_of(task: str, method: str) -> str | None:
    return TASKS[task].get("configs", {}).get(base_method(method))


def train_command(task: str, method: str, n: int, seed: int, sched: dict, out_dir: Path,
                  dataset_root: Path | None = None) -> list[str]:
    return [str(BIN / "lerobot-train"), f"--config_path={config_of(task, method)}", *_dataset_arg(dataset_root),
            *VARIANTS.get(method, (None, []))[1],
            "--policy.device=cpu", f"--dataset.episodes=[{','.join(str(i) for i in episodes(task, n))}]",
            f"--steps={sched['steps']}", f"--save_freq={sched['save_freq']}", f"--seed={seed}",
            f"--job_name={task}_{method}_{n}demos_seed{seed}", f"--output_dir={out_dir}"]


def resume_command(train_dir: Path, steps: int | None = None) -> list[str]:
    """``lerobot-train --resume=true`` from the run's last checkpoint (its own train_config: seed, data, steps
    unless ``steps`` is given: a schedule extended to the cap, ``compare_run.extend_to_cap``)."""
    return [str(BIN / "lerobot-train"),
            f"--config_path={train_dir / 'checkpoints' / 'last' / 'pretrained_model' / 'train_config.json'}",
            *([f"--steps={steps}"] if steps is not None else []), "--resume=true"]


def fit_command(task: str, n: int, out_dir: Path) -> list[str]:
    """ProMP's "training": ``lerobot-cnmp-fit-promp`` on the cell's episodes (closed form, see PROMP_LABEL)."""
    return [str(BIN / "lerobot-cnmp-fit-promp"), f"--dataset_root={REPO / TASKS[task]['dataset']}",
            "--episodes=" + ",".join(map(str, episodes(task, n))), f"--conditioning={TASKS[task]['promp']}",
            f"--output_dir={out_dir}"]


def eval_command(task: str, method: str, ckpt: Path, n_episodes: int, batch_size: int, out_dir: Path,
                 seed: int = SEED) -> list[str]:
    cmd = [str(BIN / "lerobot-eval"), f"--policy.path={ckpt}", *TASKS[task]["env"], f"--eval.n_episodes={n_episodes}",
           # one process a cell: async envs would start batch_size workers and take the core of the cell beside it
           f"--eval.batch_size={min(batch_size, n_episodes)}", "--eval.use_async_envs=false", "--policy.device=cpu",
           f"--seed={seed}",
           f"--output_dir={out_dir}"]
    if method in TASKS[task].get("env_state_copy", ()):
        cmd.append("--rename_map=" + json.dumps(RENAME_ENV_STATE))
    return cmd


def env_config(task: str):
    """The task's EnvConfig built from the same ``--env.*`` arguments that lerobot-eval gets, parsed by draccus as
    lerobot-eval parses them (``type`` picks the registered class; lists such as ``--env.cameras=[a,b]``)."""
    import draccus
    from lerobot.envs.configs import EnvConfig

    import lerobot_cnmp.sims  # noqa: F401  (registers the env types)

    args = [a.removeprefix("--env.") for a in TASKS[task]["env"]]
    kind = next(a.split("=", 1)[1] for a in args if a.startswith("type="))
    return draccus.parse(config_class=EnvConfig.get_choice_class(kind),
                         args=[f"--{a}" for a in args if not a.startswith("type=")])


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
