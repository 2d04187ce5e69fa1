"""The model card of a CNMP checkpoint: what it is, what it was trained on, its settings, its evaluation
figures when given, and how to run it.

``CNMPPolicy.generate_model_card`` returns it, so ``lerobot-train --policy.push_to_hub=true`` and
``lerobot-cnmp-push`` (:mod:`lerobot_cnmp.hub`) upload the same card. It is built offline (no Hub validation).
"""

from __future__ import annotations

BASE_TAGS = ("robotics", "lerobot", "cnmp", "movement-primitives")


def _trained_on(dataset_repo_id: str | None, cfg) -> str:
    data = f"[{dataset_repo_id}](https://huggingface.co/datasets/{dataset_repo_id})" if dataset_repo_id else "(not recorded)"
    steps = f", {cfg.steps} steps of batch {cfg.batch_size}" if cfg is not None else ""
    return data + steps


def _settings(c) -> str:
    """The network's and the training draw's settings, as markdown list lines."""
    inputs = ", ".join(f"`{k}` {list(v.shape)}" for k, v in c.input_features.items())
    lines = (
        f"- SM: {c.sm_dim} dims ({', '.join(c.sm_names or [])}); inputs: {inputs}; task parameters γ: "
        f"{c.task_dim} dims.\n"
        f"- Encoder {list(c.encoder_layers)}, query network {list(c.decoder_layers)}, n_max {c.sampling.n_max_context},\n"
        f"  m_max {c.sampling.m_max_targets}, draws per sample {c.sampling.draws_per_sample}, phase Fourier features "
        f"{c.phase_frequencies}."
    )
    if c.image_keys:
        lines += (f"\n- Images ({', '.join(f'`{k}`' for k in c.image_keys)}) through a conv encoder: 3x3 conv + 2x2 "
                  f"max-pool per width in {list(c.image_channels)}, embedding {c.image_embed_dim} per image.")
    return lines


def _results(eval_info: dict | None) -> str:
    if not eval_info:
        return "No evaluation figures were attached to this card."
    overall = eval_info.get("overall", eval_info)
    return f"`lerobot-eval`: **pc_success {overall.get('pc_success')}** over {overall.get('n_episodes')} episodes."


def _usage(c, repo_id: str, eval_info: dict | None) -> str:
    groups = list((eval_info or {}).get("per_group", {}))  # lerobot-eval's eval_info names the env
    env_type = groups[0] if groups else "<env type, e.g. cnmp_obstacle2d>"
    # the in-memory API (CNMPModel) takes SM trajectories only: image checkpoints run as a policy
    imports = "load_pretrained" if c.image_keys else "CNMPModel, load_pretrained"
    api = "" if c.image_keys else (
        f'\nmodel = CNMPModel.load("{repo_id}")                                   # or the in-memory API')
    return f"""```bash
pip install -e .   # in a lerobot-cnmp checkout: registers --policy.type=cnmp and its sims
lerobot-eval --policy.path={repo_id} --env.type={env_type} --eval.n_episodes=50 --policy.device=cpu
```

```python
from lerobot_cnmp.api import {imports}
policy, preprocessor, postprocessor = load_pretrained("{repo_id}")   # weights carry the normalization{api}
```"""


def model_card(config, dataset_repo_id, license=None, tags=None, cfg=None, eval_info: dict | None = None,
               repo_id: str | None = None):
    """A ``huggingface_hub.ModelCard`` for a CNMP policy of ``config``, trained on ``dataset_repo_id`` (or
    ``cfg.dataset.repo_id``, ``cfg`` being lerobot-train's config), with ``eval_info`` (``lerobot-eval``'s
    ``eval_info.json``) as its results."""
    from huggingface_hub import ModelCard, ModelCardData

    c = config
    repo_id = repo_id or getattr(c, "repo_id", None) or "<repo_id>"
    dataset_repo_id = dataset_repo_id or (cfg.dataset.repo_id if cfg is not None else None)
    data = ModelCardData(
        license=license or c.license or "apache-2.0", library_name="lerobot", pipeline_tag="robotics",
        tags=sorted({*BASE_TAGS, *(tags or c.tags or [])}), datasets=dataset_repo_id, model_name="cnmp",
    )
    body = f"""# CNMP policy `{repo_id}`

A Conditional Neural Movement Primitive (Seker, Imre, Piater, Ugur, RSS 2019) trained with the
lerobot-cnmp plugin as a LeRobot policy (`--policy.type=cnmp`): an encoder over
observed (phase, SM) points, mean aggregation and a Gaussian query network predict the sensorimotor (SM)
trajectory given any subset of SM points and task parameters γ; executed online with re-conditioning on
the sensed state, PD tracking and phase stopping.

## Training

- Data: {_trained_on(dataset_repo_id, cfg)}.
{_settings(c)}
- Every setting is in `config.json`; the SM and γ normalization statistics are in `model.safetensors`
  (`normalizer.*`), and the processors pass CNMP's features through.

## Evaluation

{_results(eval_info)}

## Use

{_usage(c, repo_id, eval_info)}
"""
    return ModelCard(f"---\n{data.to_yaml()}\n---\n\n{body}")
