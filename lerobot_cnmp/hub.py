"""Sharing CNMP datasets and checkpoints on the Hugging Face Hub, the LeRobot way.

    lerobot-cnmp-push --checkpoint outputs/train/checkpoints/last/pretrained_model --repo_id you/cnmp_obstacle2d
    lerobot-cnmp-push --dataset datasets/cnmp_obstacle2d --repo_id you/cnmp_obstacle2d
    lerobot-cnmp-record --sim cnmp_obstacle2d --root datasets/mine --push_to_hub --repo_id you/mine

Datasets go up through ``LeRobotDataset.push_to_hub`` with the recorder's card as the dataset description;
checkpoints (config, weights, processors with their statistics, the train config when there is one) go up
as one folder with the policy's model card (:mod:`lerobot_cnmp.policy.card`). Both come back with LeRobot's own
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


def require_online(what: str) -> None:
    """Raise HubUnavailableError, before any work, when the Hub is in offline mode (a push could not happen)."""
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


def push_dataset(root: str | Path, repo_id: str, private: bool = False) -> str:
    """Push a local CNMP dataset with ``LeRobotDataset.push_to_hub``; its card's text becomes the Hub card's
    description. Returns the dataset's URL."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = Path(root)
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"{root} is not a LeRobotDataset folder (no meta/info.json)")
    require_online(f"dataset {root}")
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
    require_online(f"checkpoint {checkpoint}")
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
