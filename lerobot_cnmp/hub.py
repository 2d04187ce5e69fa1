"""Sharing CNMP datasets and checkpoints on the Hugging Face Hub, the LeRobot way.

    lerobot-cnmp-push --checkpoint outputs/train/checkpoints/last/pretrained_model --repo_id you/cnmp_obstacle2d
    lerobot-cnmp-push --dataset datasets/cnmp_obstacle2d --repo_id you/cnmp_obstacle2d
    lerobot-cnmp-record --sim cnmp_obstacle2d --root datasets/mine --push_to_hub --repo_id you/mine

Datasets go up through ``LeRobotDataset.push_to_hub`` with the recorder's card as the dataset description;
checkpoints (config, weights, processors with their statistics, the train config when there is one) go up
as one folder with a model card (:func:`model_card`). Both come back with LeRobot's own
loaders: ``LeRobotDataset(repo_id)`` and ``lerobot_cnmp.api.load_pretrained(repo_id)`` (or
``--policy.path=repo_id``).
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

CARD_TAGS = ["cnmp", "movement-primitives", "mujoco", "lerobot-cnmp"]
PAPER = "https://www.roboticsproceedings.org/rss15/p71.pdf"


class HubUnavailableError(RuntimeError):
    """The Hub cannot be reached (offline mode or no connection); nothing was uploaded."""


def _require_online(what: str) -> None:
    from huggingface_hub import constants

    if constants.HF_HUB_OFFLINE:
        raise HubUnavailableError(
            f"cannot push {what}: the Hub is in offline mode (HF_HUB_OFFLINE=1). Unset it, log in with "
            "`hf auth login`, and retry; nothing was uploaded."
        )


def _network_errors() -> tuple[type[BaseException], ...]:
    import httpx
    import requests
    from huggingface_hub.errors import OfflineModeIsEnabled

    return (OfflineModeIsEnabled, requests.ConnectionError, httpx.ConnectError, httpx.TimeoutException, OSError)


def card_body(readme: str) -> str:
    """A card's markdown without its YAML front matter."""
    return re.sub(r"\A---\n.*?\n---\n", "", readme, count=1, flags=re.S).strip()


def model_card(config, dataset_repo_id, license=None, tags=None, cfg=None, eval_info: dict | None = None,
               repo_id: str | None = None):
    """The model card of a CNMP checkpoint (used by ``lerobot-train --policy.push_to_hub=true`` through
    ``CNMPPolicy.generate_model_card``, and by :func:`push_checkpoint`): what it is, what it was trained on,
    its settings, its evaluation figures when given, and how to run it. Built offline (no Hub validation)."""
    from huggingface_hub import ModelCard, ModelCardData

    c = config
    repo_id = repo_id or getattr(c, "repo_id", None) or "<repo_id>"
    dataset_repo_id = dataset_repo_id or (cfg.dataset.repo_id if cfg is not None else None)
    data = ModelCardData(
        license=license or c.license or "apache-2.0", library_name="lerobot", pipeline_tag="robotics",
        tags=sorted({"robotics", "lerobot", "cnmp", "movement-primitives", *(tags or c.tags or [])}),
        datasets=dataset_repo_id, model_name="cnmp",
    )
    inputs = ", ".join(f"`{k}` {list(v.shape)}" for k, v in c.input_features.items())
    trained = f"[{dataset_repo_id}](https://huggingface.co/datasets/{dataset_repo_id})" if dataset_repo_id else "(not recorded)"
    steps = f", {cfg.steps} steps of batch {cfg.batch_size}" if cfg is not None else ""
    groups = list((eval_info or {}).get("per_group", {}))  # lerobot-eval's eval_info names the env
    env_type = groups[0] if groups else "<env type, e.g. cnmp_obstacle2d>"
    images = ""
    if c.image_keys:
        images = (f"\n- Images ({', '.join(f'`{k}`' for k in c.image_keys)}) through a conv encoder: 3x3 conv + 2x2 "
                  f"max-pool per width in {list(c.image_channels)}, embedding {c.image_embed_dim} per image.")
    # the in-memory API (CNMPModel) takes SM trajectories only: image checkpoints run as a policy
    imports = "load_pretrained" if c.image_keys else "CNMPModel, load_pretrained"
    api = ("" if c.image_keys else
           f'\nmodel = CNMPModel.load("{repo_id}")                                   # or the in-memory API')
    results = "No evaluation figures were attached to this card."
    if eval_info:
        overall = eval_info.get("overall", eval_info)
        results = (f"`lerobot-eval`: **pc_success {overall.get('pc_success')}** over "
                   f"{overall.get('n_episodes')} episodes.")
    body = f"""# CNMP policy `{repo_id}`

A Conditional Neural Movement Primitive (Seker, Imre, Piater, Ugur, RSS 2019) trained with the
lerobot-cnmp plugin as a LeRobot policy (`--policy.type=cnmp`): an encoder over
observed (phase, SM) points, mean aggregation and a Gaussian query network predict the sensorimotor (SM)
trajectory given any subset of SM points and task parameters γ; executed online with re-conditioning on
the sensed state, PD tracking and phase stopping.

## Training

- Data: {trained}{steps}.
- SM: {c.sm_dim} dims ({', '.join(c.sm_names or [])}); inputs: {inputs}; task parameters γ: {c.task_dim} dims.
- Encoder {list(c.encoder_layers)}, query network {list(c.decoder_layers)}, n_max {c.n_max_context},
  m_max {c.m_max_targets}, draws per sample {c.draws_per_sample}, phase Fourier features {c.phase_frequencies}.{images}
- Every setting is in `config.json`; the SM and γ normalization statistics are in `model.safetensors`
  (`normalizer.*`), and the processors pass CNMP's features through.

## Evaluation

{results}

## Use

```bash
pip install -e .   # in a lerobot-cnmp checkout: registers --policy.type=cnmp and its sims
lerobot-eval --policy.path={repo_id} --env.type={env_type} --eval.n_episodes=50 --policy.device=cpu
```

```python
from lerobot_cnmp.api import {imports}
policy, preprocessor, postprocessor = load_pretrained("{repo_id}")   # weights carry the normalization{api}
```
"""
    return ModelCard(f"---\n{data.to_yaml()}\n---\n\n{body}")


def push_dataset(root: str | Path, repo_id: str, private: bool = False) -> str:
    """Push a local CNMP dataset with ``LeRobotDataset.push_to_hub``; its card's text becomes the Hub card's
    description. Returns the dataset's URL."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = Path(root)
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"{root} is not a LeRobotDataset folder (no meta/info.json)")
    _require_online(f"dataset {root}")
    readme = root / "README.md"
    description = card_body(readme.read_text()) if readme.is_file() else None
    ds = LeRobotDataset(repo_id, root=root)
    try:
        ds.push_to_hub(tags=CARD_TAGS, license="apache-2.0", private=private, paper=PAPER,
                       dataset_description=description)
    except _network_errors() as e:
        raise HubUnavailableError(f"cannot push dataset {root} to {repo_id}: the Hub is unreachable ({e})") from e
    return f"https://huggingface.co/datasets/{repo_id}"


def push_checkpoint(checkpoint: str | Path, repo_id: str, private: bool = False,
                    eval_info: dict | None = None) -> str:
    """Push a CNMP checkpoint folder (``pretrained_model`` of ``lerobot-train`` or ``CNMPModel.save``) with a
    model card; ``eval_info`` (e.g. ``lerobot-eval``'s ``eval_info.json``) adds its figures to the card.
    Returns the model's URL."""
    from huggingface_hub import HfApi

    from lerobot_cnmp.api import load_pretrained

    checkpoint = Path(checkpoint)
    policy, _, _ = load_pretrained(checkpoint)  # a CNMP checkpoint with its processors, or a clear error
    _require_online(f"checkpoint {checkpoint}")
    dataset = None
    train_cfg = checkpoint / "train_config.json"
    if train_cfg.is_file():
        dataset = json.loads(train_cfg.read_text()).get("dataset", {}).get("repo_id")
    card = policy.generate_model_card(dataset, "cnmp", None, None, eval_info=eval_info, repo_id=repo_id)
    card.save(str(checkpoint / "README.md"))
    try:
        api = HfApi()
        api.create_repo(repo_id=repo_id, repo_type="model", private=private, exist_ok=True)
        api.upload_folder(repo_id=repo_id, repo_type="model", folder_path=checkpoint,
                          commit_message="Upload CNMP checkpoint (config, weights, processors, card)",
                          allow_patterns=["*.safetensors", "*.json", "*.md"])
    except _network_errors() as e:
        raise HubUnavailableError(f"cannot push {checkpoint} to {repo_id}: the Hub is unreachable ({e})") from e
    return f"https://huggingface.co/{repo_id}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="lerobot-cnmp-push", description=__doc__.split("\n\n")[0])
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--checkpoint", help="a CNMP checkpoint folder (config.json, model.safetensors, processors)")
    what.add_argument("--dataset", help="a local LeRobotDataset folder")
    p.add_argument("--repo_id", required=True, help="the Hub repository, e.g. you/cnmp_obstacle2d")
    p.add_argument("--eval_info", help="lerobot-eval's eval_info.json, for the model card")
    p.add_argument("--private", action="store_true")
    args = p.parse_args(argv)
    try:
        if args.dataset:
            url = push_dataset(args.dataset, args.repo_id, args.private)
        else:
            info = json.loads(Path(args.eval_info).read_text()) if args.eval_info else None
            url = push_checkpoint(args.checkpoint, args.repo_id, args.private, info)
    except (HubUnavailableError, FileNotFoundError, ValueError) as e:
        p.error(str(e))
    print(f"pushed to {url}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
