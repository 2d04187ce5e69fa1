"""What the bench scripts share: paths, the config's CNMP built for the in-memory API, and one-env
closed-loop helpers (an env observation as the policy's batch, the SM predicted in the env's units)."""

from __future__ import annotations

import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs" / "cnmp_obstacle2d.json"
DATASET = REPO / "datasets" / "cnmp_obstacle2d"
CHECKPOINT = REPO / "outputs" / "main" / "train" / "checkpoints" / "last" / "pretrained_model"

API_FIELDS = ("encoder_layers", "decoder_layers", "min_std", "n_max_context", "m_max_targets", "context_in_targets",
              "draws_per_sample", "partial_obs_prob", "sensed_obs_prob", "optimizer_lr", "scheduler_decay_lr", "phase_frequencies",
              "feedback_dims", "tracking_dims", "pd_dims", "pd_kp", "pd_kd", "phase_stop_threshold")
"""The config's policy fields that the in-memory API takes over (model, sampling, optimizer; the execution
names are the old top-level aliases; a config's ``execution`` section is passed as a whole)."""


def policy_batch(pre, obs: dict) -> dict:
    """One env's gymnasium observation (``pixels`` a dict of images) as the policy's preprocessed batch of 1,
    as ``lerobot-eval``'s rollout builds it (LeRobot's ``preprocess_observation``, then the preprocessor)."""
    from lerobot.envs.utils import preprocess_observation

    batched = {k: ({n: v[None] for n, v in x.items()} if isinstance(x, dict) else x[None]) for k, x in obs.items()}
    return pre({**preprocess_observation(batched), "task": [""]})


def predict_sm(policy, pre, post, batch: dict, phase, query_phases):
    """(μ, σ) of the SM at ``query_phases`` in the env's units, [len(query_phases), D] numpy each: the
    CNMP conditioned as the executor is at ``phase`` (the conditions, the start, the state sensed in
    ``batch``)."""
    import torch

    phase = torch.as_tensor(phase, dtype=torch.float32).reshape(1)
    query = torch.as_tensor(query_phases, dtype=torch.float32).reshape(1, -1)
    with torch.no_grad():
        mean, std = policy.network()(policy.executor.execution_context(batch, phase), query)
    n = policy.normalizer
    return post(n.sm_inverse(mean[0])).numpy(), (std[0] * n.sm_std).numpy()


def make_sim(env_cfg, policy, n_envs: int):
    """(vector env, env preprocessor, env postprocessor) of a sim's ``EnvConfig``, built as ``lerobot-eval``
    builds them, for LeRobot's ``rollout``."""
    from lerobot.envs.factory import make_env, make_env_pre_post_processors

    env = next(iter(make_env(env_cfg, n_envs=n_envs)[env_cfg.type].values()))
    return (env, *make_env_pre_post_processors(env_cfg, policy.config))


def config(path: Path = CONFIG) -> dict:
    return json.loads(Path(path).read_text())


def api_model(cfg: dict | None = None):
    """A ``CNMPModel`` with the training config's model, sampling and learning-rate settings."""
    from lerobot_cnmp.api import CNMPModel

    from lerobot_cnmp.executor import ExecutionConfig

    pol = (cfg or config())["policy"]
    kw = {k: pol[k] for k in API_FIELDS if k in pol}
    if "execution" in pol:  # the configs' execution settings (lerobot_cnmp.executor.ExecutionConfig)
        kw["execution"] = ExecutionConfig(**pol["execution"])
    return CNMPModel(**kw)


def checkpoint_or_train(path: str | Path | None, out_dir: Path, steps: int | None = None,
                        config_path: Path = CONFIG) -> Path:
    """``path`` if it is a checkpoint; else fit the config's CNMP with the in-memory API for the config's
    steps and batch size (the same model, sampling and schedule as ``lerobot-train``; whole demos instead
    of windows; γ when the dataset has it) and save it to ``out_dir``."""
    if path is not None and (Path(path) / "config.json").is_file():
        return Path(path)
    from lerobot_cnmp.data import load_demos

    cfg = config(config_path)
    steps = steps or cfg["steps"]
    print(f"no checkpoint at {path}: fitting {Path(config_path).name}'s CNMP with the in-memory API ({steps} steps)")
    data = load_demos(REPO / cfg["dataset"]["root"])
    model = api_model(cfg).fit(data["demos"], task_params=data["task_params"], steps=steps,
                               batch_size=cfg["batch_size"], seed=cfg.get("seed", 0))
    return model.save(out_dir)
