"""Conditional Neural Movement Primitives (Seker, Imre, Piater, Ugur, RSS 2019).

Read top-down:

1. ``sample_context_and_targets`` -- the training step's draw (paper Sec. III-B): from each demonstration
   in the batch, n ~ U{1..n_max} observations (t_i, SM(t_i)) and m ~ U{1..m_max} queries (t_q, SM(t_q)).
2. ``CNMP`` -- pure torch:  r_i = E([t_i, γ, SM_i ⊙ mask_i, mask_i]);  r = mean_i r_i  (``aggregate``);
   (μ_q, σ_q) = Q([t_q, γ, r])  (``decode``);  loss = -log N(SM(t_q) | μ_q, σ_q)  (``nll``, Eq. 1).
3. ``CNMPPolicy`` -- the LeRobot face: turns ``lerobot-train`` batches into episode samples for (1)-(2),
   and executes online in ``select_action`` (condition on goals + current state, predict the next SM).

Everything works on padded batches with validity masks; padded entries never change an output.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_cnmp.conditions import decode_conditions
from lerobot_cnmp.configuration_cnmp import TASK_PARAMS, CNMPConfig

PHASE_KEY = f"{ACTION}_phase"
"""Optional batch key: the phase of every ``action`` window entry. The in-memory API provides it; for
``lerobot-train`` batches it is derived from the dataset's episode table."""


# --------------------------------------------------------------------------------------------------------
# Data containers
# --------------------------------------------------------------------------------------------------------


@dataclass
class Episodes:
    """Demonstrations (or windows of them) in a batch: ``values[b, j]`` is SM at ``phase[b, j]``."""

    values: Tensor  # [B, W, D]
    phase: Tensor  # [B, W] in [0, 1]
    valid: Tensor  # [B, W] bool
    task_params: Tensor | None = None  # [B, G]

    def repeat(self, k: int) -> Episodes:
        """Each episode k times (for k independent draws from it)."""
        rep = lambda x: None if x is None else x.repeat_interleave(k, dim=0)  # noqa: E731
        return Episodes(rep(self.values), rep(self.phase), rep(self.valid), rep(self.task_params))


@dataclass
class Context:
    """Observations to condition on: SM ``values`` at ``phase``, ``mask`` = which SM dims are given."""

    phase: Tensor  # [B, N]
    values: Tensor  # [B, N, D]
    mask: Tensor  # [B, N, D] float 0/1
    valid: Tensor  # [B, N] bool
    task_params: Tensor | None = None  # [B, G]


@dataclass
class Targets:
    phase: Tensor  # [B, M]
    values: Tensor  # [B, M, D]
    valid: Tensor  # [B, M] bool


# --------------------------------------------------------------------------------------------------------
# 1. The training step's draw
# --------------------------------------------------------------------------------------------------------


def _random_valid_order(valid: Tensor, generator: torch.Generator | None) -> Tensor:
    """A random permutation of each row's indices with the valid entries first."""
    scores = torch.rand(valid.shape, generator=generator, device=valid.device)
    scores = scores.masked_fill(~valid, 2.0)
    return scores.argsort(dim=1)


def _uniform_count(upper: Tensor, generator: torch.Generator | None) -> Tensor:
    """Per row, an integer uniform in {1, ..., upper} (upper >= 1)."""
    u = torch.rand(upper.shape, generator=generator, device=upper.device)
    return 1 + (u * upper).long().clamp(max=upper - 1)


def sample_context_and_targets(
    episodes: Episodes,
    n_max: int,
    m_max: int,
    partial_obs_prob: float = 0.0,
    generator: torch.Generator | None = None,
    context_in_targets: bool = False,
) -> tuple[Context, Targets]:
    """Sample, per episode, n ~ U{1..min(n_max, #valid)} observations and m ~ U{1..min(m_max, #valid)}
    queries among its valid entries (plus the n observations themselves with ``context_in_targets``).
    With probability ``partial_obs_prob`` an observation constrains only a random non-empty subset of the
    SM dimensions."""
    values, phase, valid = episodes.values, episodes.phase, episodes.valid
    B, W, D = values.shape  # noqa: N806
    n_valid = valid.sum(dim=1)
    if bool((n_valid < 1).any()):
        raise ValueError("every episode in the batch needs at least one valid (non-padded) frame")

    def draw(k_max: int):
        order = _random_valid_order(valid, generator)[:, : min(k_max, W)]
        count = _uniform_count(n_valid.clamp(max=k_max), generator)
        keep = torch.arange(order.shape[1], device=values.device)[None, :] < count[:, None]
        idx = order
        return (
            phase.gather(1, idx),
            values.gather(1, idx[..., None].expand(-1, -1, D)),
            keep,
        )

    c_phase, c_values, c_valid = draw(n_max)
    t_phase, t_values, t_valid = draw(m_max)

    mask = torch.ones_like(c_values)
    if partial_obs_prob > 0 and D > 1:
        bits = torch.rand(c_values.shape, generator=generator, device=values.device) < 0.5
        # Guarantee a non-empty subset: force one random dim on.
        forced = torch.randint(D, c_values.shape[:2], generator=generator, device=values.device)
        bits = bits | F.one_hot(forced, D).bool()
        partial = torch.rand(c_values.shape[:2], generator=generator, device=values.device) < partial_obs_prob
        mask = torch.where(partial[..., None], bits.float(), mask)

    context = Context(c_phase, c_values, mask, c_valid, episodes.task_params)
    if context_in_targets:
        t_phase, t_values, t_valid = (torch.cat(p, 1) for p in ((c_phase, t_phase), (c_values, t_values), (c_valid, t_valid)))
    return context, Targets(t_phase, t_values, t_valid)


# --------------------------------------------------------------------------------------------------------
# 2. The model
# --------------------------------------------------------------------------------------------------------


def mlp(in_dim: int, widths: tuple[int, ...]) -> nn.Sequential:
    """Linear layers with ReLU between them (none after the last)."""
    layers: list[nn.Module] = []
    for i, w in enumerate(widths):
        layers.append(nn.Linear(in_dim, w))
        if i < len(widths) - 1:
            layers.append(nn.ReLU())
        in_dim = w
    return nn.Sequential(*layers)


def run_mlp(layers: nn.Sequential, x: Tensor, start: int = 0) -> Tensor:
    """``layers(x)`` from layer ``start`` on, without the per-module call overhead (a few µs per layer on CPU,
    which is most of a control step's time). Same parameters, same result."""
    for layer in list(layers)[start:]:
        x = F.linear(x, layer.weight, layer.bias) if isinstance(layer, nn.Linear) else F.relu(x, inplace=True)
    return x


class ConvEncoder(nn.Module):
    """Image -> embedding (paper Sec. IV-B): per width in ``channels`` a 3x3 conv, ReLU and 2x2 max-pool
    (the paper: 8, 16, 32, 64), then a linear layer to ``embed_dim``."""

    def __init__(self, in_shape: tuple[int, int, int], channels: tuple[int, ...], embed_dim: int):
        super().__init__()
        c, h, w = in_shape
        layers: list[nn.Module] = []
        for width in channels:
            layers += [nn.Conv2d(c, width, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2)]
            c, h, w = width, h // 2, w // 2
        self.conv = nn.Sequential(*layers)
        self.project = nn.Linear(c * h * w, embed_dim)

    def forward(self, images: Tensor) -> Tensor:
        return self.project(self.conv(images).flatten(1))


class CNMP(nn.Module):
    """Encoder E -> mean aggregation -> query network Q with a Gaussian output (pure torch)."""

    def __init__(
        self,
        sm_dim: int,
        task_dim: int = 0,
        encoder_layers: tuple[int, ...] = (128, 128, 128),
        decoder_layers: tuple[int, ...] = (128, 128, 128),
        min_std: float = 0.01,
        phase_frequencies: int = 0,
    ):
        super().__init__()
        self.sm_dim, self.task_dim, self.min_std = sm_dim, task_dim, min_std
        self.register_buffer(
            "frequencies", torch.pi * torch.arange(1, phase_frequencies + 1, dtype=torch.float32), persistent=False
        )
        t_dim = 1 + 2 * phase_frequencies
        self.encoder = mlp(t_dim + task_dim + 2 * sm_dim, tuple(encoder_layers))
        self.decoder = mlp(t_dim + task_dim + encoder_layers[-1], (*decoder_layers, 2 * sm_dim))

    def phase_features(self, t: Tensor) -> Tensor:
        """[..., 1 + 2K]: t itself, plus sin / cos of k·π·t for k = 1..K (none by default, as in the paper)."""
        t = t[..., None]
        if self.frequencies.numel() == 0:
            return t
        angles = t * self.frequencies
        return torch.cat([t, angles.sin(), angles.cos()], dim=-1)

    def _inputs(self, head: list[Tensor], tail: list[Tensor], task_params: Tensor | None, n: int) -> Tensor:
        """[*head, γ, *tail] along the last dim, γ repeated over the n points (the input layout of E and Q)."""
        if self.task_dim:
            if task_params is None:
                raise ValueError(f"this CNMP was trained with {self.task_dim} task parameters γ; none given")
            if task_params.shape[-1] != self.task_dim:
                raise ValueError(
                    f"task parameters γ have {task_params.shape[-1]} dims, the model expects {self.task_dim}"
                )
            head = [*head, task_params[:, None, :].expand(-1, n, -1)]
        parts = head + tail
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)

    def encode(self, context: Context) -> Tensor:
        """r_i = E(t_i, γ, SM_i ⊙ mask_i, mask_i): one representation per observation, [B, N, R]."""
        x = self._inputs(
            [self.phase_features(context.phase)],
            [context.values * context.mask, context.mask],
            context.task_params,
            context.phase.shape[1],
        )
        return run_mlp(self.encoder, x)

    @staticmethod
    def aggregate(r_i: Tensor, valid: Tensor) -> Tensor:
        """r = mean of the valid r_i, [B, R] (order- and padding-invariant)."""
        w = valid.to(r_i.dtype)
        return torch.bmm(w[:, None, :], r_i)[:, 0] / w.sum(dim=1, keepdim=True).clamp(min=1.0)

    def decode(self, r: Tensor, query_phase: Tensor, task_params: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """(μ, σ) = Q(t_q, γ, r) for every query phase, each [B, M, D]; σ = min_std + softplus(.).

        Q's first layer is linear in its input [t_q, γ, r], so it is computed as W_t·t_q + (W_γr·[γ, r] + b):
        the second term once per episode, not once per query (a 200-query trajectory costs little more than
        its last layers)."""
        first = self.decoder[0]
        t_dim = 1 + 2 * self.frequencies.numel()
        per_episode = self._inputs([], [r[:, None, :]], task_params, 1)  # [B, 1, G + R]
        h = F.linear(per_episode, first.weight[:, t_dim:], first.bias) + F.linear(
            self.phase_features(query_phase), first.weight[:, :t_dim]
        )
        out = run_mlp(self.decoder, h, start=1)
        mean, raw = out.split(self.sm_dim, dim=-1)
        return mean, self.min_std + F.softplus(raw)

    def condition(self, context: Context) -> Tensor:
        """The representation r of a context (encode + aggregate)."""
        return self.aggregate(self.encode(context), context.valid)

    def forward(self, context: Context, query_phase: Tensor) -> tuple[Tensor, Tensor]:
        return self.decode(self.condition(context), query_phase, context.task_params)

    @staticmethod
    def nll(mean: Tensor, std: Tensor, targets: Targets) -> Tensor:
        """Eq. 1: -log N(SM(t_q) | μ_q, σ_q), summed over SM dims, averaged over the valid queries."""
        per_dim = 0.5 * ((targets.values - mean) / std) ** 2 + std.log() + 0.5 * np.log(2 * np.pi)
        per_query = per_dim.sum(dim=-1)
        w = targets.valid.to(per_query.dtype)
        return (per_query * w).sum() / w.sum().clamp(min=1.0)

    def training_loss(self, context: Context, targets: Targets) -> tuple[Tensor, dict]:
        """One training step's loss on a drawn (context, targets) pair, with monitoring figures."""
        mean, std = self(context, targets.phase)
        loss = self.nll(mean, std, targets)
        with torch.no_grad():
            w = targets.valid[..., None].to(mean.dtype)
            mae = ((mean - targets.values).abs() * w).sum() / (w.sum() * mean.shape[-1]).clamp(min=1.0)
            mean_std = (std * w).sum() / (w.sum() * mean.shape[-1]).clamp(min=1.0)
        return loss, {"nll": loss.item(), "mae": mae.item(), "std": mean_std.item()}


class NumpyCNMP:
    """A frozen numpy copy of a :class:`CNMP` for execution on CPU: the same inference equations (encode,
    masked-mean aggregate, decode with Q's first layer split) on the same weights.

    A batch-1 control step is ~25 small ops; torch spends several µs of dispatch on each, numpy about one,
    so this runs a control step 2-4x faster on CPU. Training stays in torch; the policy rebuilds this copy
    whenever the weights change. ``tests/test_model.py`` checks it against :class:`CNMP`."""

    def __init__(self, model: CNMP):
        def layers(seq: nn.Sequential) -> list[tuple[np.ndarray, np.ndarray]]:
            return [(m.weight.detach().cpu().numpy().T.copy(), m.bias.detach().cpu().numpy().copy())
                    for m in seq if isinstance(m, nn.Linear)]

        self.encoder, decoder = layers(model.encoder), layers(model.decoder)
        self.frequencies = model.frequencies.cpu().numpy()
        self.sm_dim, self.task_dim, self.min_std = model.sm_dim, model.task_dim, model.min_std
        t_dim = 1 + 2 * self.frequencies.size
        (w, b), self.decoder = decoder[0], decoder[1:]
        self.decoder_t, self.decoder_rest, self.decoder_bias = w[:t_dim], w[t_dim:], b

    def phase_features(self, t: np.ndarray) -> np.ndarray:
        t = t[..., None]
        if not self.frequencies.size:
            return t
        angles = t * self.frequencies
        return np.concatenate([t, np.sin(angles), np.cos(angles)], axis=-1)

    @staticmethod
    def _mlp(x: np.ndarray, layers) -> np.ndarray:
        for i, (w, b) in enumerate(layers):
            x = x @ w
            x += b
            if i < len(layers) - 1:
                np.maximum(x, 0.0, out=x)
        return x

    def __call__(self, context: Context, query_phase: Tensor) -> tuple[Tensor, Tensor]:
        phase, values, mask = context.phase.numpy(), context.values.numpy(), context.mask.numpy()
        valid = context.valid.numpy().astype(np.float32)
        gamma = None if context.task_params is None or not self.task_dim else context.task_params.numpy()
        head = [self.phase_features(phase)]
        if gamma is not None:
            head.append(np.broadcast_to(gamma[:, None, :], (*phase.shape, self.task_dim)))
        r_i = self._mlp(np.concatenate([*head, values * mask, mask], axis=-1), self.encoder)  # E
        r = (valid[:, None, :] @ r_i)[:, 0] / np.maximum(valid.sum(1, keepdims=True), 1.0)  # mean of valid r_i
        if gamma is not None:
            r = np.concatenate([gamma, r], axis=-1)
        h = (r @ self.decoder_rest + self.decoder_bias)[:, None, :] + self.phase_features(query_phase.numpy()) @ self.decoder_t
        np.maximum(h, 0.0, out=h)
        out = self._mlp(h, self.decoder)  # Q
        mean, raw = out[..., : self.sm_dim], out[..., self.sm_dim :]
        return torch.from_numpy(np.ascontiguousarray(mean)), torch.from_numpy(self.min_std + np.logaddexp(0.0, raw))


# --------------------------------------------------------------------------------------------------------
# 3. The LeRobot policy
# --------------------------------------------------------------------------------------------------------


def check_finite(name: str, x: Tensor) -> None:
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains NaN or infinite values")


class CNMPPolicy(PreTrainedPolicy):
    """CNMP as a LeRobot policy.

    Training (``forward``): each batch item is a window of one demonstration's ``action`` sequence
    (``action_delta_indices``) with ``action_is_pad``; the phase of each entry is frame / (T - 1), from the
    dataset's episode table (given by ``lerobot-train``) or from ``action_phase`` when the batch has it.

    Execution (``select_action``, the paper's loop of Sec. III / Fig. 3): per env, the policy keeps a phase
    τ (0 after ``reset``). Each step it
    1. advances τ by Δ unless the tracking error |sensed SM - SM commanded last step| exceeds
       ``phase_stop_threshold`` (with ``online_feedback``; open loop always advances);
    2. conditions on the episode's conditions (``observation.environment_state``), on the state sensed at the
       first step (t = 0, ``condition_on_start``) and, with ``online_feedback``, on the current sensed state;
    3. predicts SM(τ) (μ, σ) and sends the PD command s + kp·e + kd·(e - e_prev), e = μ - s (kp may be scaled
       down where σ is large). The sensed state at step k is what step k - 1 commanded, so it enters the
       context at phase τ - Δ.
    """

    config_class = CNMPConfig
    name = "cnmp"

    def __init__(self, config: CNMPConfig, dataset_meta=None, **kwargs):
        if not isinstance(config, CNMPConfig):
            raise TypeError(
                f"CNMPPolicy needs a CNMPConfig; got {type(config).__name__} (a checkpoint of another policy type?)"
            )
        super().__init__(config)
        config.validate_features()
        self.config = config
        # One conv encoder per image feature; its embedding joins γ as the episode-level input of E and Q.
        self.image_encoders = nn.ModuleDict({
            key.replace(".", "_"): ConvEncoder(tuple(config.input_features[key].shape), config.image_channels,
                                               config.image_embed_dim)
            for key in config.image_keys
        })
        self.model = CNMP(
            sm_dim=config.sm_dim,
            task_dim=config.episode_dim,
            encoder_layers=config.encoder_layers,
            decoder_layers=config.decoder_layers,
            min_std=config.min_std,
            phase_frequencies=config.phase_frequencies,
        )
        self.register_buffer(
            "window_offsets", torch.tensor(config.action_delta_indices, dtype=torch.long), persistent=False
        )
        # Episode table of the training dataset (absolute index of frame 0, length); not saved.
        self.register_buffer("episode_from", torch.zeros(0, dtype=torch.long), persistent=False)
        self.register_buffer("episode_length", torch.zeros(0, dtype=torch.long), persistent=False)
        if dataset_meta is not None:
            self.set_episode_table(dataset_meta)
        self._numpy_model: NumpyCNMP | None = None  # execution copy of self.model, see executor()
        self._numpy_key: tuple | None = None
        self.reset()

    @classmethod
    def _load_as_safetensor(cls, model, model_file: str, map_location: str, strict: bool):
        """Load weights strictly: a checkpoint of another CNMP configuration is an error, not a silent
        partial load."""
        try:
            return super()._load_as_safetensor(model, model_file, map_location, strict=True)
        except RuntimeError as e:
            raise ValueError(
                f"the weights in {model_file} do not fit this CNMP configuration (layer sizes, SM or γ dims "
                f"differ): {e}"
            ) from e

    # ---- sharing --------------------------------------------------------------------------------------

    def generate_model_card(self, dataset_repo_id, model_type="cnmp", license=None, tags=None, cfg=None,
                            dataset_meta=None, eval_info: dict | None = None, repo_id: str | None = None):
        """The model card of a CNMP checkpoint (used by ``lerobot-train --policy.push_to_hub=true`` and by
        ``lerobot_cnmp.hub.push_checkpoint``): what it is, what it was trained on, its settings, its
        evaluation figures when given, and how to run it. Built offline (no Hub validation call)."""
        from huggingface_hub import ModelCard, ModelCardData

        c = self.config
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
- SM (`action`): {c.sm_dim} dims; inputs: {inputs}; task parameters γ: {c.task_dim} dims.
- Encoder {list(c.encoder_layers)}, query network {list(c.decoder_layers)}, n_max {c.n_max_context},
  m_max {c.m_max_targets}, draws per sample {c.draws_per_sample}, phase Fourier features {c.phase_frequencies}.{images}
- Every setting is in `config.json`; the normalization statistics are in the processor files.

## Evaluation

{results}

## Use

```bash
pip install -e .   # in a lerobot-cnmp checkout: registers --policy.type=cnmp and its sims
lerobot-eval --policy.path={repo_id} --env.type={env_type} --eval.n_episodes=50 --policy.device=cpu
```

```python
from lerobot_cnmp.api import {imports}
policy, preprocessor, postprocessor = load_pretrained("{repo_id}")   # the checkpoint's own statistics{api}
```
"""
        return ModelCard(f"---\n{data.to_yaml()}\n---\n\n{body}")

    # ---- training -------------------------------------------------------------------------------------

    def set_episode_table(self, dataset_meta) -> None:
        """Read each episode's first absolute index and length from LeRobot dataset metadata."""
        episodes = dataset_meta.episodes
        ep_index = np.asarray(episodes["episode_index"], dtype=np.int64)
        size = int(ep_index.max()) + 1 if len(ep_index) else 0
        frm = np.zeros(size, dtype=np.int64)
        length = np.zeros(size, dtype=np.int64)
        frm[ep_index] = np.asarray(episodes["dataset_from_index"], dtype=np.int64)
        length[ep_index] = np.asarray(episodes["length"], dtype=np.int64)
        longest = int(length.max()) if size else 0
        if longest > self.config.max_episode_length:
            raise ValueError(
                f"the dataset has an episode of {longest} frames but max_episode_length is "
                f"{self.config.max_episode_length}: set --policy.max_episode_length={longest} or more"
            )
        if size and int(length[ep_index].min()) < 2:
            raise ValueError("every demonstration needs at least 2 frames to define a phase")
        self.episode_from = torch.from_numpy(frm).to(self.episode_from.device)
        self.episode_length = torch.from_numpy(length).to(self.episode_length.device)
        if self.config.demo_length is None and size:
            self.config.demo_length = int(np.median(length[ep_index]))

    def episodes_from_batch(self, batch: dict[str, Tensor]) -> Episodes:
        """A ``lerobot-train`` batch (or an in-memory one with ``action_phase``) as :class:`Episodes`."""
        if ACTION not in batch:
            raise KeyError(f"CNMP training batches need {ACTION!r}; got keys {sorted(batch)}")
        values = batch[ACTION]
        if values.ndim != 3 or values.shape[-1] != self.config.sm_dim:
            raise ValueError(
                f"{ACTION!r} must be a window [batch, frames, {self.config.sm_dim}], got {tuple(values.shape)}; "
                "train with the config's action_delta_indices"
            )
        pad = batch.get(f"{ACTION}_is_pad")
        valid = torch.ones(values.shape[:2], dtype=torch.bool, device=values.device) if pad is None else ~pad
        if PHASE_KEY in batch:
            phase = batch[PHASE_KEY].to(values.dtype)
        else:
            if self.episode_length.numel() == 0:
                raise RuntimeError(
                    "CNMP needs the dataset's episode table to know each frame's phase: build the policy with "
                    "`dataset_meta=` (lerobot-train does) or put 'action_phase' in the batch"
                )
            if values.shape[1] != self.window_offsets.numel():
                raise ValueError(
                    f"{ACTION!r} window has {values.shape[1]} frames but the config's action_delta_indices has "
                    f"{self.window_offsets.numel()}"
                )
            ep = batch["episode_index"].long().reshape(-1)
            frame = batch["index"].long().reshape(-1) - self.episode_from[ep]
            length = self.episode_length[ep]
            frames = frame[:, None] + self.window_offsets[None, :]
            phase = frames.to(values.dtype) / (length[:, None] - 1).to(values.dtype)
        valid = valid & (phase >= 0) & (phase <= 1)
        check_finite(ACTION, torch.where(valid[..., None], values, torch.zeros_like(values)))
        return Episodes(values, phase.clamp(0, 1), valid, self._episode_inputs(batch))

    def forward(self, batch: dict[str, Tensor], generator: torch.Generator | None = None) -> tuple[Tensor, dict]:
        c = self.config
        episodes = self.episodes_from_batch(batch)
        if c.draws_per_sample > 1:
            episodes = episodes.repeat(c.draws_per_sample)
        context, targets = sample_context_and_targets(
            episodes, c.n_max_context, c.m_max_targets, c.partial_obs_prob, generator, c.context_in_targets
        )
        return self.model.training_loss(context, targets)

    def get_optim_params(self) -> dict:
        return self.parameters()

    # ---- execution ------------------------------------------------------------------------------------

    def reset(self) -> None:
        """Restart every env's execution state (called by lerobot-eval at each episode start)."""
        self._phase: Tensor | None = None  # τ per env
        self._start: Tensor | None = None  # state sensed at the first step (condition_on_start)
        self._target: Tensor | None = None  # SM commanded at the previous step (normalized)
        self._error: Tensor | None = None  # previous PD error e, for the D term

    @property
    def phase_step(self) -> float:
        if self.config.phase_step is not None:
            return self.config.phase_step
        if self.config.demo_length is None:
            raise RuntimeError(
                "demo_length is unknown: train on a dataset (it is set from the episode lengths) or set "
                "--policy.demo_length or --policy.phase_step"
            )
        return 1.0 / (self.config.demo_length - 1)

    @staticmethod
    def _dims_mask(like: Tensor, dims) -> Tensor:
        if dims is None:
            return torch.ones_like(like)
        mask = torch.zeros_like(like)
        mask[..., list(dims)] = 1.0
        return mask

    def _feedback_mask(self, like: Tensor) -> Tensor:
        return self._dims_mask(like, self.config.feedback_dims)

    def tracking_error(self, state: Tensor) -> Tensor:
        """Per env, max over the tracked dims (``tracking_dims``, else the fed-back ones) of
        |sensed SM - SM commanded at the previous step|."""
        if self._target is None:
            return torch.zeros(state.shape[0], device=state.device, dtype=state.dtype)
        c = self.config
        dims = c.tracking_dims if c.tracking_dims is not None else c.feedback_dims
        return ((state - self._target).abs() * self._dims_mask(state, dims)).amax(dim=-1)

    def pd_gains(self, std: Tensor) -> tuple[Tensor, Tensor]:
        """(kp, kd) per env and SM dim: kp constant or scaled by sigma_ref / σ within [kp_min, kp_max]; outside
        ``pd_dims`` kp = 1 and kd = 0 (the prediction itself is commanded)."""
        c = self.config
        kp = torch.full_like(std, c.pd_kp) if not c.sigma_scaled_gains else (c.pd_kp * c.sigma_ref / std).clamp(
            c.kp_min, c.kp_max)
        kd = torch.full_like(std, c.pd_kd)
        if c.pd_dims is not None:
            on = self._dims_mask(std, c.pd_dims)
            kp, kd = on * kp + (1 - on), on * kd
        return kp, kd

    def _episode_inputs(self, batch: dict[str, Tensor]) -> Tensor | None:
        """The episode-level input of E and Q: γ (``observation.task_params``) and the embedding of each image
        feature, [B, episode_dim]; None when there is neither."""
        parts = []
        if self.config.task_dim:
            if TASK_PARAMS not in batch:
                raise KeyError(f"this CNMP is conditioned on task parameters: the batch needs {TASK_PARAMS!r}")
            g = batch[TASK_PARAMS]
            g = g.reshape(g.shape[0], -1) if g.ndim != 3 else g[:, 0]  # a window of γ: all frames are equal
            check_finite(TASK_PARAMS, g)
            parts.append(g)
        for key in self.config.image_keys:
            if key not in batch:
                raise KeyError(f"this CNMP is conditioned on the image {key!r}; the batch has {sorted(batch)}")
            img = batch[key]
            img = img[:, 0] if img.ndim == 5 else img  # a window of frames: the episode's image is constant
            check_finite(key, img)
            parts.append(self.image_encoders[key.replace(".", "_")](img))
        if not parts:
            return None
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)

    def execution_context(self, batch: dict[str, Tensor], phase: Tensor) -> Context:
        """Conditions from ``environment_state``, the start state at t = 0 and (with ``online_feedback``) the
        current sensed state at τ - Δ."""
        d = self.config.sm_dim
        phases, values, masks, valids = [], [], [], []
        if OBS_ENV_STATE in batch and self.config.max_conditions:
            env = batch[OBS_ENV_STATE]
            check_finite(OBS_ENV_STATE, env)
            present, c_phase, c_values, c_mask = decode_conditions(env, d)
            given = present > 0.5
            if bool(((c_phase < 0) | (c_phase > 1))[given].any()):
                raise ValueError("a condition in environment_state has a phase outside [0, 1]")
            phases.append(c_phase)
            values.append(c_values)
            masks.append(c_mask)
            valids.append(given & (c_mask.sum(-1) > 0))
        if self.config.online_feedback or self.config.condition_on_start:
            if OBS_STATE not in batch:
                raise KeyError(f"online_feedback and condition_on_start need {OBS_STATE!r} in the observation")
            state = batch[OBS_STATE]
            if state.shape[-1] != d:
                raise ValueError(f"{OBS_STATE!r} has {state.shape[-1]} dims, the SM has {d}")
            check_finite(OBS_STATE, state)
        if self.config.condition_on_start:
            if self._start is None or self._start.shape[0] != state.shape[0]:
                self._start = state.clone()
            phases.append(torch.zeros_like(phase)[:, None])
            values.append(self._start[:, None, :])
            masks.append(torch.ones_like(state)[:, None, :])
            valids.append(torch.ones_like(phase, dtype=torch.bool)[:, None])
        if self.config.online_feedback:
            phases.append((phase - self.phase_step).clamp(min=0.0)[:, None])
            values.append(state[:, None, :])
            masks.append(self._feedback_mask(state)[:, None, :])
            valids.append(torch.ones_like(phase, dtype=torch.bool)[:, None])
        if not phases:
            raise ValueError(
                "nothing to condition on: the observation has no environment_state conditions and both "
                "online_feedback and condition_on_start are off"
            )
        valid = torch.cat(valids, dim=1)
        if not bool(valid.any(dim=1).all()):
            raise ValueError("an env in the batch has no condition to condition on (empty context)")
        return Context(torch.cat(phases, 1), torch.cat(values, 1), torch.cat(masks, 1), valid, self._episode_inputs(batch))

    def _ensure_state(self, batch: dict[str, Tensor]) -> Tensor:
        ref = batch[OBS_STATE] if OBS_STATE in batch else batch[OBS_ENV_STATE]
        if self._phase is None or self._phase.shape[0] != ref.shape[0]:
            self.reset()
            self._phase = torch.zeros(ref.shape[0], device=ref.device, dtype=ref.dtype)
        return ref

    def executor(self):
        """The network that execution runs: the numpy copy on CPU (``numpy_execution``, rebuilt whenever a
        weight changes), else the torch model."""
        if not self.config.numpy_execution or self.training or self.model.frequencies.device.type != "cpu":
            return self.model
        key = tuple((p.data_ptr(), p._version) for p in self.model.parameters())
        if self._numpy_key != key:
            self._numpy_model, self._numpy_key = NumpyCNMP(self.model), key
        return self._numpy_model

    def _predict(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        """(μ, σ) of the SM at each env's current phase, [B, 1, D] each."""
        return self.executor()(self.execution_context(batch, self._phase), self._phase[:, None])

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """The SM predicted at the current phase, [B, 1, D] (no phase update, no PD)."""
        self._ensure_state(batch)
        return self._predict(batch)[0]

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """One step of the execution loop (see the class docstring), for every env of the batch."""
        c = self.config
        self._ensure_state(batch)  # resets the state of a new batch of envs
        state = batch.get(OBS_STATE)
        if self._target is not None:  # not the first step: the phase may advance
            advance = torch.ones_like(self._phase, dtype=torch.bool)
            if c.online_feedback and c.phase_stop_threshold is not None and state is not None:
                advance = self.tracking_error(state) <= c.phase_stop_threshold
            self._phase = torch.where(advance, (self._phase + self.phase_step).clamp(max=1.0), self._phase)
        mean, std = self._predict(batch)
        target, std = mean[:, 0], std[:, 0]
        action = target
        if c.online_feedback and state is not None:
            error = target - state
            previous = self._error if self._error is not None else error
            kp, kd = self.pd_gains(std)
            action = state + kp * error + kd * (error - previous)
            self._error = error
        self._target = target
        return action
