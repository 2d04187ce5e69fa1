"""What the bench scripts share: paths, the config's CNMP built for the in-memory API, and one-env
closed-loop helpers (an env observation as the policy's batch, the SM predicted in the env's units)."""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from pathlib import Path

from bench.settings import add_dataclass_arguments, dataclass_settings

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs" / "cnmp_obstacle2d.json"
DATASET = REPO / "datasets" / "cnmp_obstacle2d"
CHECKPOINT = REPO / "outputs" / "main" / "train" / "checkpoints" / "last" / "pretrained_model"

DATASET_RESOLVED = ("sm", "sm_names", "task_features", "use_task_params", "demo_duration_s", "dataset_fps")
"""CNMPConfig fields that training fills in from the data when the config leaves them unset (the SM and γ
features, the timing): a config's or a run's values for them are not settings it was given."""

API_DECIDES = ("state_tracks_action", *DATASET_RESOLVED)
"""CNMPConfig fields the in-memory API sets itself from the demos it is given (the tied SM layout and
:data:`DATASET_RESOLVED`), so a config's values for them are not passed on."""


def policy_batch(pre, obs: dict) -> dict:
    """One env's gymnasium observation (``pixels`` a dict of images) as the policy's preprocessed batch of 1,
    as ``lerobot-eval``'s rollout builds it (LeRobot's ``preprocess_observation``, then the preprocessor)."""
    from lerobot.envs.utils import preprocess_observation

    batched = {k: ({n: v[None] for n, v in x.items()} if isinstance(x, dict) else x[None]) for k, x in obs.items()}
    return pre({**preprocess_observation(batched), "task": [""]})


def read_frames(root: Path):
    """Every frame of a local LeRobotDataset's parquet files (``data/*/*.parquet``) as one pandas DataFrame."""
    import pandas as pd

    files = sorted((Path(root) / "data").rglob("*.parquet"))
    if not files:
        raise FileNotFoundError(f"no LeRobotDataset at {root} (no data/*/*.parquet)")
    return pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)


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
    """A ``CNMPModel`` with the training config's CNMP settings (model, sampling, optimizer, execution): every
    ``CNMPConfig`` field the config's ``policy`` section sets, except LeRobot's own (device, features, hub) and
    :data:`API_DECIDES`. An image-conditioned config is an error: the API fits SM trajectories, not images."""
    import dataclasses

    import draccus
    from lerobot.configs.policies import PreTrainedConfig

    from lerobot_cnmp.api import CNMPModel
    from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig

    pol = (cfg or config())["policy"]
    if pol.get("use_images"):
        raise ValueError("the in-memory API fits SM trajectories, not images: this config sets use_images "
                         "(train it with lerobot-train)")
    lerobot_own = {f.name for f in dataclasses.fields(PreTrainedConfig)}
    given = {k: v for k, v in pol.items()
             if k in CNMPConfig.__dataclass_fields__ and k not in lerobot_own and k not in API_DECIDES}
    decoded = draccus.decode(CNMPConfig, given)  # the JSON's lists and sections as the dataclass's types
    return CNMPModel(**{k: getattr(decoded, k) for k in given})


def torch_threads(given: int | None, environ=os.environ) -> tuple[int, str]:
    """(threads, where from) for both sides of a training comparison (the API and lerobot-train): ``given``
    (``--threads``), else the environment's ``OMP_NUM_THREADS``, else one per CPU core. A value that is not an
    integer >= 1 is an error."""
    if given is not None:
        n, source = given, "--threads"
    elif environ.get("OMP_NUM_THREADS", "").strip():
        text, source = environ["OMP_NUM_THREADS"].strip(), "OMP_NUM_THREADS"
        try:
            n = int(text)
        except ValueError:
            raise ValueError(f"OMP_NUM_THREADS must be an integer >= 1, got {text!r}") from None
    else:
        n, source = os.cpu_count() or 1, "CPU cores"
    if n < 1:
        raise ValueError(f"the number of torch threads ({source}) must be >= 1, got {n}")
    return n, source


def child_environment(threads: int, environ=os.environ) -> dict:
    """A ``lerobot-train`` subprocess's environment: this one's, offline, with ``threads`` torch threads."""
    return {**environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": str(threads)}


def add_threads_argument(parser) -> None:
    """``--threads``: the torch threads of both sides of a training comparison (:func:`torch_threads`)."""
    parser.add_argument("--threads", type=int, default=None,
                        help="torch threads of both sides, the API's and lerobot-train's (default: OMP_NUM_THREADS, "
                             "else one per CPU core)")


class MissingCheckpointError(FileNotFoundError):
    """A bench was pointed at a checkpoint that is not there, and not asked to train one (``--train``)."""


PROVENANCE_FILE = "bench_provenance.json"
"""Written by :func:`resolve_checkpoint` into a checkpoint it fitted itself: how it was trained."""


def _matching_config(train_cfg: dict) -> Path | None:
    """The ``configs/*.json`` whose dataset root, steps, seed and job name are those of a ``lerobot-train``
    run's ``train_config.json`` (LeRobot does not store the ``--config_path`` it was given)."""
    keys = (("dataset", "root"), ("steps",), ("seed",), ("job_name",))

    def pick(d, k):
        for part in k:
            d = d.get(part) if isinstance(d, dict) else None
        return d

    for cand in sorted((REPO / "configs").glob("*.json")):
        try:
            c = json.loads(cand.read_text())
        except (OSError, ValueError):
            continue
        if all(pick(c, k) == pick(train_cfg, k) for k in keys):
            return cand
    return None


def _mixture_fields() -> tuple[str, ...]:
    from lerobot_cnmp.policy.configuration_cnmp import MixtureConfig

    return tuple(f.name for f in dataclasses.fields(MixtureConfig))


MIXTURE_FIELDS = _mixture_fields()
"""The mixture decoder's settings that a mixture bench takes on the command line and reports: the fields of
``CNMPConfig.mixture`` (their types, defaults and allowed values come from MixtureConfig)."""


def add_mixture_arguments(p) -> None:
    """The :data:`MIXTURE_FIELDS` as a mixture bench's options, each None (the config's) unless given."""
    from lerobot_cnmp.policy.configuration_cnmp import EXPERT_SELECTION, MixtureConfig

    add_dataclass_arguments(p, MixtureConfig, only=MIXTURE_FIELDS, choices={"expert_selection": EXPERT_SELECTION})


def mixture_settings(args) -> dict:
    """The :data:`MIXTURE_FIELDS` given on the command line (those not None): the ``mixture`` section's overrides
    (pass them as ``CNMPModel(..., mixture=settings)``)."""
    from lerobot_cnmp.policy.configuration_cnmp import MixtureConfig

    return dataclass_settings(args, MixtureConfig, only=MIXTURE_FIELDS)


def mixture_report(config) -> dict:
    """The mixture settings a fitted model's ``CNMPConfig`` trained with, for a bench's JSON."""
    return {k: getattr(config.mixture, k) for k in MIXTURE_FIELDS}


def _policy_overrides(train_cfg: dict, committed: dict) -> dict:
    """``--policy.<name>`` values of a ``lerobot-train`` run that differ from the committed config it matches
    (dotted names inside a nested section). For a CNMP run: the settings that change what is trained, i.e.
    every CNMPConfig field but LeRobot's own (device, features, hub), the execution section and
    :data:`DATASET_RESOLVED`, compared with the committed config as CNMPConfig reads it (its defaults filled in)."""
    got, want = train_cfg.get("policy") or {}, committed.get("policy") or {}
    if got.get("type") != "cnmp":
        return {k: v for k, v in got.items() if k in want and v != want[k] and k not in ("device", "pretrained_path")}
    import dataclasses

    import draccus
    from lerobot.configs.policies import PreTrainedConfig

    from lerobot_cnmp.execution.config import ExecutionConfig
    from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig

    skip = ({f.name for f in dataclasses.fields(PreTrainedConfig)}
            | {f.name for f in dataclasses.fields(ExecutionConfig)} | {"execution", *DATASET_RESOLVED})
    fields = [f.name for f in dataclasses.fields(CNMPConfig) if f.name not in skip]
    resolved = draccus.encode(draccus.decode(CNMPConfig, {k: v for k, v in want.items() if k != "type"}))
    out: dict = {}

    def differ(prefix: str, a, b) -> None:  # a: the run's value, b: the committed one
        if isinstance(a, dict) and isinstance(b, dict):
            for k in a:
                if k in b:
                    differ(f"{prefix}.{k}", a[k], b[k])
        elif a != b:
            out[prefix] = a

    for k in fields:
        if k in got:
            differ(k, got[k], resolved.get(k))
    return out


def provenance(path: str | Path) -> dict:
    """Which checkpoint produced a bench's figures: its path, training step, training command and a hash of
    its weights (``model.safetensors``). For a ``lerobot-train`` checkpoint the step is read from
    ``training_state/training_step.json`` and the command rebuilt from ``train_config.json`` (the committed
    config with the same dataset, steps, seed and job name, and the run's output dir); for a checkpoint a
    bench fitted itself, from the record it wrote (``bench_provenance.json``)."""
    import hashlib

    path = Path(path).absolute()
    if not (path / "config.json").is_file():
        raise MissingCheckpointError(f"no checkpoint at {path} (no config.json)")
    weights = path / "model.safetensors"
    out = {"path": str(path), "step": None, "training_command": None, "trained_by": None,
           "weights_sha256": hashlib.sha256(weights.read_bytes()).hexdigest()[:16] if weights.is_file() else None}
    own = path / PROVENANCE_FILE
    fit_info = path.parent / "fit_info.json"  # a ProMP policy written by lerobot-cnmp-fit-promp
    if fit_info.is_file() and not (path / "train_config.json").is_file():
        info = json.loads(fit_info.read_text())
        out.update(step=0, trained_by="lerobot-cnmp-fit-promp (closed form)", training_command=info.get("command"),
                   fit_info=str(fit_info))
        return out
    if own.is_file():
        out.update(json.loads(own.read_text()))
        return out
    step_file = path.parent / "training_state" / "training_step.json"
    if step_file.is_file():
        out["step"] = int(json.loads(step_file.read_text())["step"])
    train_file = path / "train_config.json"
    if train_file.is_file():
        tc = json.loads(train_file.read_text())
        out["trained_by"] = "lerobot-train"
        out["train_config"] = str(train_file)
        match = _matching_config(tc)
        if match is not None:
            flags = "".join(f" --policy.{k}={json.dumps(v, separators=(',', ':'))}"
                            for k, v in _policy_overrides(tc, json.loads(match.read_text())).items())
            out["training_command"] = (f"lerobot-train --config_path={match.relative_to(REPO)}{flags} "
                                       f"--output_dir={tc.get('output_dir')}")
        else:
            out["training_command"] = (f"lerobot-train (no committed config matches; see {train_file}: dataset "
                                       f"{tc['dataset'].get('root') or tc['dataset'].get('repo_id')}, "
                                       f"{tc.get('steps')} steps, seed {tc.get('seed')})")
        if out["step"] is None:
            out["step"] = tc.get("steps")
    else:
        out["trained_by"] = "unknown (no train_config.json, no bench_provenance.json)"
    return out


def resolve_checkpoint(path: str | Path | None, *, train: bool, out_dir: Path, steps: int | None = None,
                       config_path: Path = CONFIG) -> Path:
    """``path`` if it is a checkpoint folder (holding ``config.json``). Otherwise, with ``train``, fit the
    config's CNMP with the in-memory API (:func:`fit_checkpoint`) into ``out_dir``; without it, raise
    :class:`MissingCheckpointError` saying how to get one. A bench never trains silently."""
    if path is not None and (Path(path) / "config.json").is_file():
        return Path(path)
    if path is not None and Path(path).exists():
        hint = Path(path) / "pretrained_model"
        more = f" (did you mean {hint}?)" if (hint / "config.json").is_file() else ""
        if not train:
            raise MissingCheckpointError(f"{path} is not a checkpoint folder: it has no config.json{more}")
    if not train:
        rel = Path(config_path)
        rel = rel.relative_to(REPO) if rel.is_absolute() and REPO in rel.parents else rel
        raise MissingCheckpointError(
            f"no checkpoint at {path}: train one with `lerobot-train --config_path={rel} --output_dir=...` and "
            f"pass its checkpoints/last/pretrained_model as --checkpoint, or pass --train to fit {Path(config_path).name}'s "
            "CNMP with the in-memory API first")
    return fit_checkpoint(out_dir, steps=steps, config_path=config_path)


def fit_checkpoint(out_dir: Path, steps: int | None = None, config_path: Path = CONFIG) -> Path:
    """Fit the config's CNMP with the in-memory API for the config's steps and batch size (the same model,
    sampling and schedule as ``lerobot-train``; whole demos instead of windows; γ when the dataset has it),
    save it to ``out_dir`` with a ``bench_provenance.json`` recording the call. A config the API cannot fit
    as written (images, the joint SM layout's own settings) raises :class:`MissingCheckpointError` naming it,
    rather than fitting a different model."""
    from lerobot_cnmp.data.demos import load_demos

    cfg = config(config_path)
    steps = steps or cfg["steps"]
    rel = Path(config_path)
    rel = rel.relative_to(REPO) if rel.is_absolute() and REPO in rel.parents else rel
    print(f"--train: fitting {Path(config_path).name}'s CNMP with the in-memory API ({steps} steps)", flush=True)
    data = load_demos(REPO / cfg["dataset"]["root"])
    try:
        model = api_model(cfg).fit(data["demos"], task_params=data["task_params"], steps=steps,
                                   batch_size=cfg["batch_size"], seed=cfg.get("seed", 0), progress=False)
    except ValueError as e:
        raise MissingCheckpointError(
            f"--train cannot fit {rel}'s CNMP with the in-memory API ({e}): train it with "
            f"`lerobot-train --config_path={rel} --output_dir=...` and pass its "
            "checkpoints/last/pretrained_model as --checkpoint") from e
    path = model.save(out_dir)
    (Path(path) / PROVENANCE_FILE).write_text(json.dumps({
        "trained_by": "lerobot_cnmp.api.CNMPModel.fit (bench --train)",
        "step": steps,
        "training_command": (f"bench.common.fit_checkpoint(config_path={str(rel)!r}, steps={steps}): "
                             f"CNMPModel(<{rel}'s policy fields>).fit(load_demos({cfg['dataset']['root']!r}), "
                             f"steps={steps}, batch_size={cfg['batch_size']}, seed={cfg.get('seed', 0)})"),
    }, indent=2))
    return path


def add_checkpoint_args(parser, default: Path, what: str = "a CNMP checkpoint") -> None:
    """``--checkpoint`` (default ``default``) and ``--train`` (fit one with the API if it is missing)."""
    parser.add_argument("--checkpoint", default=str(default), help=f"{what} (a pretrained_model folder)")
    parser.add_argument("--train", action="store_true",
                        help="if --checkpoint is missing, fit the config's CNMP with the in-memory API first "
                             "(without it a missing checkpoint is an error)")


def add_episode_args(parser, seed: int, episodes: int = 50) -> None:
    """``--episodes`` (>= 1, checked by :func:`parse_episode_args`) and ``--seed`` (the first reset seed)."""
    parser.add_argument("--episodes", type=int, default=episodes)
    parser.add_argument("--seed", type=int, default=seed)


def parse_episode_args(parser):
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    return args


def load_checkpoint_policy(args, name: str, config_path: Path):
    """(checkpoint, policy in eval mode, preprocessor, postprocessor) of a bench's ``--checkpoint`` /
    ``--train`` (:func:`checkpoint_from_args`)."""
    from lerobot_cnmp.api import load_pretrained

    ckpt = checkpoint_from_args(args, name, config_path=config_path)
    policy, pre, post = load_pretrained(ckpt)
    policy.eval()
    return ckpt, policy, pre, post


def fitted_dir(name: str) -> Path:
    """Where ``--train`` saves the checkpoint it fits for ``name`` (kept, so the JSON's path stays valid)."""
    return REPO / "outputs" / "bench" / "fitted" / name


def checkpoint_from_args(args, name: str, config_path: Path = CONFIG) -> Path:
    """:func:`resolve_checkpoint` of a bench's ``--checkpoint`` / ``--train``; a missing checkpoint ends the
    script with the error's message (exit status 2), not a traceback."""
    try:
        return resolve_checkpoint(args.checkpoint, train=args.train, out_dir=fitted_dir(name), config_path=config_path)
    except MissingCheckpointError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
