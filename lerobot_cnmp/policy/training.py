"""From a ``lerobot-train`` batch to the CNMP's training loss.

A batch item names an episode (``episode_index``, from the frame LeRobot's loader drew); its observations and
queries are drawn from that whole episode's SM, held in memory (the policy's
:class:`~lerobot_cnmp.data.bank.EpisodeBank`, read from the dataset when LeRobot builds the policy with
``dataset_meta``, or given by the in-memory API). Two kinds of draws: the paper's random draw
(:func:`~lerobot_cnmp.model.sampling.sample_context_and_targets` on :func:`episodes_for`'s frames) and, with
``feedback_draw_weight`` > 0, execution-shaped draws (:func:`feedback_draws`). Each function takes the
:class:`~lerobot_cnmp.policy.modeling_cnmp.CNMPPolicy` whose demonstrations, normalizer and encoders it uses.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from lerobot_cnmp.data.bank import EpisodeBank
from lerobot_cnmp.model.cnmp import Context, Episodes, Targets
from lerobot_cnmp.model.sampling import sample_context_and_targets
from lerobot_cnmp.policy.inputs import embed, join


def set_bank(policy, bank: EpisodeBank, fps: float | None) -> None:
    """Train on ``bank``'s demonstrations; for a new policy, take the normalization statistics, the demos'
    duration and fps from them (a checkpoint's statistics load over these afterwards: fine-tuning)."""
    c = policy.config
    if bank.values.shape[1] != c.sm_dim:
        raise ValueError(f"the demonstrations have {bank.values.shape[1]} SM dims, the policy {c.sm_dim}")
    policy.bank = bank
    if not policy.normalizer.ready:
        policy.normalizer.set(bank.sm_stats(), bank.task_stats())
    if c.demo_duration_s is None:
        c.demo_duration_s = bank.median_duration_s()
    if c.dataset_fps is None:
        c.dataset_fps = fps if fps is not None else 1.0


def set_dataset(policy, dataset_meta) -> None:
    """Read the training demonstrations' SM and γ from a LeRobot dataset (its metadata's local root), and the
    first frames of its image features."""
    set_bank(policy, EpisodeBank.from_dataset(dataset_meta.root, policy.config.spec), fps=float(dataset_meta.fps))
    if policy.config.image_keys:
        policy._first_frames = FirstFrames(dataset_meta, policy.config.image_keys)
        if policy.config.image_encoder.center:  # the demos' mean first frame (a checkpoint's loads over it)
            frames = policy._first_frames(torch.tensor(sorted(policy._first_frames.first)))
            for key in policy.config.image_keys:
                policy.image_encoders[key.replace(".", "_")].mean_image.copy_(frames[key].mean(dim=0))


def training_inputs(policy, episode_index: Tensor, draws: int, generator: torch.Generator | None = None
                    ) -> Tensor | None:
    """The episode-level input (normalized γ, the conv encoder's embedding of the first frame, randomly
    shifted by ``image_encoder.shift``) of each named episode, computed once and repeated over its ``draws``;
    None when there is neither."""
    c = policy.config
    dev = policy.normalizer.sm_std.device
    gamma = policy.bank.task_params_of(episode_index)
    parts = []
    if gamma is not None and c.task_dim:
        parts.append(policy.normalizer.task(gamma.to(dev)))
    if c.image_keys:
        if policy._first_frames is None:
            raise RuntimeError("this CNMP conditions on images: build it with `dataset_meta=` to train")
        images = policy._first_frames(episode_index)
        shift = c.image_encoder.shift
        parts += [embed(policy.image_encoders, k, images[k].to(dev), shift=shift, generator=generator)
                  for k in c.image_keys]
    inputs = join(parts)
    if inputs is not None and draws > 1:
        inputs = inputs.repeat_interleave(draws, dim=0)
    return inputs


def episodes_for(policy, episode_index: Tensor, generator: torch.Generator | None = None, draws: int = 1
                 ) -> Episodes:
    """``draws`` independent draws per named episode (rows ``b * draws .. b * draws + draws - 1``): each
    n_max + m_max frames uniform over the whole episode, normalized. The episode-level input (γ, the conv
    encoder's embedding of the first frame) is computed once per named episode."""
    if policy.bank is None:
        raise RuntimeError(
            "CNMP trains on demonstrations it holds in memory: build the policy with `dataset_meta=` "
            "(lerobot-train does) or train with lerobot_cnmp.api.CNMPModel.fit")
    policy.normalizer.require()
    c = policy.config
    dev = policy.normalizer.sm_std.device
    episode_index = episode_index.reshape(-1)
    values, phase = policy.bank.draw(episode_index.repeat_interleave(draws), c.sampling.n_max_context + c.sampling.m_max_targets,
                                     generator)
    values = policy.normalizer.sm(values.to(dev))
    valid = torch.ones(phase.shape, dtype=torch.bool, device=dev)
    return Episodes(values, phase.to(dev), valid, training_inputs(policy, episode_index, draws, generator))


def feedback_draws(policy, episode_index: Tensor, generator: torch.Generator | None = None,
                   inputs: Tensor | None = None) -> tuple[Context, Targets]:
    """Execution-shaped draws (``feedback_draw_weight``), ``draws_per_sample`` per named episode: the context is
    the sensed dims at the episode's first frame (with ``condition_on_start``) and at a uniform frame j; the
    queries are j, j + 1 and ``feedback_draw_queries`` (default ``m_max_targets``) uniform frames. ``inputs``:
    the episode-level input already computed for these draws (``episodes_for``'s ``task_params``); None
    computes it."""
    c = policy.config
    dev = policy.normalizer.sm_std.device
    episode_index = episode_index.reshape(-1)
    if inputs is None:
        inputs = training_inputs(policy, episode_index, c.sampling.draws_per_sample, generator)
    m = c.sampling.m_max_targets if c.sampling.feedback_draw_queries is None else int(c.sampling.feedback_draw_queries)
    values, phase = policy.bank.draw_feedback(episode_index.repeat_interleave(c.sampling.draws_per_sample), m, generator)
    values, phase = policy.normalizer.sm(values.to(dev)), phase.to(dev)
    first = 0 if c.execution.condition_on_start else 1
    n_ctx = 2 - first
    b = values.shape[0]
    mask = policy.sensed_only_mask[None, None, :].expand(b, n_ctx, -1)
    context = Context(phase[:, first:2], values[:, first:2], mask,
                      torch.ones(b, n_ctx, dtype=torch.bool, device=dev), inputs)
    targets = Targets(phase[:, 1:], values[:, 1:], torch.ones(b, phase.shape[1] - 1, dtype=torch.bool, device=dev))
    return context, targets


def training_loss(policy, batch: dict[str, Tensor], generator: torch.Generator | None = None
                  ) -> tuple[Tensor, dict]:
    """The loss of one ``lerobot-train`` step: the network's ``training_loss`` on the random draws of the
    batch's episodes, mixed with that on execution-shaped draws by ``feedback_draw_weight``."""
    c = policy.config
    if "episode_index" not in batch:
        raise KeyError(f"CNMP training batches need 'episode_index' (LeRobot's loader gives it); got {sorted(batch)}")
    episodes = episodes_for(policy, batch["episode_index"], generator, draws=c.sampling.draws_per_sample)
    context, targets = sample_context_and_targets(
        episodes, c.sampling.n_max_context, c.sampling.m_max_targets, c.sampling.partial_obs_prob, generator, c.sampling.context_in_targets,
        policy.sensed_only_mask, c.sampling.sensed_obs_prob,
    )
    loss, info = policy.model.training_loss(context, targets, c.sampling.draws_per_sample)
    w = c.sampling.feedback_draw_weight
    if w > 0:
        fb_draws = feedback_draws(policy, batch["episode_index"], generator, inputs=episodes.task_params)
        fb_loss, fb_info = policy.model.training_loss(*fb_draws, c.sampling.draws_per_sample)
        info = {**info, "nll_random": info["nll"], "nll_feedback": fb_info["nll"]}
        loss = (1.0 - w) * loss + w * fb_loss
        info["nll"] = loss.item()
    if policy.final_point_head is not None:  # auxiliary: the images' embedding -> the episode's SM at point_phases
        embedding = episodes.task_params[:: c.sampling.draws_per_sample, c.task_dim:]
        phases = c.image_encoder.point_phases
        points = policy.normalizer.sm(policy.bank.points_of(batch["episode_index"], phases).to(embedding.device))
        # squared error averaged over the SM dims, summed over the phases: each point weighs as the last alone
        error = (policy.final_point_head(embedding) - points.flatten(1)).square().view(points.shape)
        aux = error.mean(dim=-1).sum(dim=-1).mean()
        loss = loss + c.image_encoder.final_point_weight * aux
        info = {**info, "final_point_mse": aux.item()}
    return loss, info


class FirstFrames:
    """Each training episode's first camera frame per image feature, read once from the dataset (LeRobot's own
    decoder) and kept as uint8 on the CPU: the image the conv encoder sees for that episode."""

    def __init__(self, dataset_meta, keys: list[str]):
        self.meta, self.keys = dataset_meta, list(keys)
        self.cache: dict[int, dict[str, Tensor]] = {}
        self._dataset = None
        eps = dataset_meta.episodes
        self.first = dict(zip(np.asarray(eps["episode_index"]).tolist(), np.asarray(eps["dataset_from_index"]).tolist(),
                              strict=True))

    def _load(self, ep: int) -> dict[str, Tensor]:
        if self._dataset is None:
            from lerobot.datasets.lerobot_dataset import LeRobotDataset

            self._dataset = LeRobotDataset(self.meta.repo_id, root=self.meta.root)
        mapping = self._dataset.absolute_to_relative_idx
        absolute = int(self.first[ep])
        item = self._dataset[mapping[absolute] if mapping else absolute]
        return {k: (item[k].clamp(0, 1) * 255).round().to(torch.uint8) for k in self.keys}

    def __call__(self, episode_index: Tensor) -> dict[str, Tensor]:
        eps = episode_index.reshape(-1).tolist()
        for e in set(eps):
            if e not in self.cache:
                if e not in self.first:
                    raise KeyError(f"episode {e} is not in the dataset")
                self.cache[e] = self._load(e)
        return {k: torch.stack([self.cache[e][k] for e in eps]).float() / 255.0 for k in self.keys}
