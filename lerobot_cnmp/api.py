"""The in-memory Python API: fit a CNMP on demonstrations held in arrays, condition, predict.

    from lerobot_cnmp.api import CNMPModel, Condition
    model = CNMPModel().fit(demos, steps=3000)             # demos: [N, T, D] (or a list of [T_i, D])
    mean, std = model.predict(np.linspace(0, 1, 200),      # [200, D] each
                              [Condition(0.5, (0.5, 0.4))])

Training goes through ``CNMPPolicy.forward`` -- the same loss and sampler as ``lerobot-train`` -- and
``save`` writes a LeRobot checkpoint (config, weights, processors) that ``lerobot-eval`` can run.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import trange

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_cnmp.data.bank import EpisodeBank
from lerobot_cnmp.data.demos import pad_demos, query_phases
from lerobot_cnmp.data.sm_spec import TASK_PARAMS
from lerobot_cnmp.execution.conditions import Condition, check_conditions, layout_size
from lerobot_cnmp.model.cnmp import Context
from lerobot_cnmp.model.mixture import mixture_of, n_experts
from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig
from lerobot_cnmp.policy.modeling_cnmp import CNMPPolicy

__all__ = ["CNMPModel", "Condition", "load_pretrained", "pad_demos", "sm_stats"]


class CNMPModel:
    """A CNMP in memory: ``fit``, ``predict``, ``save`` / ``load``. Works in the data's own units."""

    def __init__(
        self, config: CNMPConfig | None = None, device: str = "cpu", max_conditions: int = 4, **overrides
    ):
        """``max_conditions``: condition slots of ``observation.environment_state`` a saved checkpoint
        declares, so that it runs in a CNMP env (``lerobot-eval``) as a ``lerobot-train`` one does.

        The demos are SM trajectories in the tied layout (``state_tracks_action``): the SM is what a saved
        checkpoint commands as ``action`` and senses as ``observation.state``."""
        self.config = config
        self.max_conditions = max_conditions
        self.overrides = overrides
        self.device = device
        self.policy: CNMPPolicy | None = None

    def _stat(self, name: str):
        return None if self.policy is None else getattr(self.policy.normalizer, name).cpu().numpy()

    sm_mean = property(lambda self: self._stat("sm_mean"))
    sm_std = property(lambda self: self._stat("sm_std"))
    task_mean = property(lambda self: None if not self.config or not self.config.task_dim else self._stat("task_mean"))
    task_std = property(lambda self: None if not self.config or not self.config.task_dim else self._stat("task_std"))

    # ---- fitting --------------------------------------------------------------------------------------

    def _build(self, sm_dim: int, task_dim: int) -> None:
        cfg = self.config or CNMPConfig(device=self.device, state_tracks_action=True, **self.overrides)
        cfg.device = self.device
        cfg.output_features = {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(sm_dim,))}
        # The execution features a CNMP env provides: sensed SM state and condition slots.
        cfg.input_features = {
            OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(sm_dim,)),
            OBS_ENV_STATE: PolicyFeature(type=FeatureType.ENV, shape=(layout_size(sm_dim, self.max_conditions),)),
        }
        if task_dim:
            cfg.input_features[TASK_PARAMS] = PolicyFeature(type=FeatureType.STATE, shape=(task_dim,))
        self.config = cfg
        self.policy = CNMPPolicy(cfg).to(self.device)

    def fit(
        self,
        demos,
        task_params=None,
        steps: int = 3000,
        batch_size: int = 64,
        seed: int = 0,
        progress: bool = True,
        callback=None,
        callback_every: int = 500,
        fps: float | None = None,
    ) -> CNMPModel:
        """Train on demonstrations ``[N, T, D]`` (or a list of ``[T_i, D]``), optionally with per-demo task
        parameters γ ``[N, G]``, recorded at ``fps`` (None: one frame per control step). Each step draws
        ``batch_size`` demos (each with probability ∝ its length, as ``lerobot-train`` does) and, from each,
        observations and queries over the whole demo: the same sampler and loss as ``lerobot-train``.

        ``callback(steps_done, model)``, if given, runs every ``callback_every`` steps and after the last one,
        with the model in eval mode (e.g. to track a validation error); returning True stops training there."""
        values, valid, _ = pad_demos(demos)
        seqs = [values[i, : int(valid[i].sum())] for i in range(len(values))]
        n, _, d = values.shape
        gamma = None
        if task_params is not None:
            gamma = np.asarray(task_params, dtype=np.float32)
            if gamma.ndim != 2 or gamma.shape[0] != n:
                raise ValueError(f"task_params must be [N={n}, G]; got shape {gamma.shape}")
            if not np.isfinite(gamma).all():
                raise ValueError("task_params contain NaN or infinite values")
        if steps < 1 or batch_size < 1 or callback_every < 1:
            raise ValueError(
                f"steps, batch_size and callback_every must be >= 1; got {steps}, {batch_size}, {callback_every}"
            )
        task_dim = 0 if gamma is None else gamma.shape[1]
        if self.policy is not None:
            self._check_refit(d, task_dim)
        bank = EpisodeBank.from_arrays(seqs, gamma, fps)
        torch.manual_seed(seed)  # before the network is built: a new model's initialization follows the seed too
        if self.policy is None:
            self._build(d, task_dim)
        self.policy.set_bank(bank, fps)
        gen = torch.Generator(device="cpu").manual_seed(seed)
        torch.manual_seed(seed)
        policy = self.policy
        policy.train()
        optim = self.config.get_optimizer_preset().build(policy.get_optim_params())
        sched_cfg = self.config.get_scheduler_preset()
        sched = None if sched_cfg is None else sched_cfg.build(optim, steps)
        clip = self.config.optimizer_grad_clip_norm
        self.history: list[dict] = []
        bar = trange(steps, desc="CNMP fit", disable=not progress)
        for step in bar:
            batch = {"episode_index": bank.sample_episodes(batch_size, gen)}
            loss, info = policy.forward(batch, generator=gen)
            optim.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(policy.parameters(), clip)
            optim.step()
            if sched is not None:
                sched.step()
            if step % 50 == 0 or step == steps - 1:
                self.history.append({"step": step, **info})
                bar.set_postfix(nll=f"{info['nll']:.3f}", mae=f"{info['mae']:.3f}")
            if callback is not None and ((step + 1) % callback_every == 0 or step == steps - 1):
                policy.eval()
                stop = callback(step + 1, self)
                policy.train()
                if stop:
                    break
        bar.close()
        policy.eval()
        return self

    def _check_refit(self, sm_dim: int, task_dim: int) -> None:
        """A re-fit trains the same network further: the demos' SM and γ sizes must be the ones it was built for."""
        if sm_dim != self.config.sm_dim:
            raise ValueError(f"demos have SM dimension {sm_dim}, the model has {self.config.sm_dim}")
        had = self.config.task_dim
        if task_dim == had:
            return
        if not had:
            raise ValueError(f"this model was fitted without task parameters γ; a re-fit cannot add {task_dim} (the "
                             "network's input size is fixed): fit a new CNMPModel with task_params")
        if not task_dim:
            raise ValueError(f"this model was fitted with {had} task parameters γ; give task_params [N, {had}] to "
                             "fit it again, or fit a new CNMPModel without them")
        raise ValueError(f"task_params have {task_dim} columns; this model was fitted with {had} task parameters γ")

    # ---- prediction -----------------------------------------------------------------------------------

    def _norm_task(self, gamma: np.ndarray) -> np.ndarray:
        return ((gamma - self.task_mean) / self.task_std).astype(np.float32)

    def _require_fitted(self) -> None:
        if self.policy is None:
            raise RuntimeError("the model is not fitted: call fit(demos) or CNMPModel.load(path) first")

    def context(self, conditions: list[Condition], task_params=None) -> Context:
        """Normalized CNMP context for a list of conditions (SM units) and optional γ."""
        self._require_fitted()
        d = self.config.sm_dim
        if not conditions:
            raise ValueError("empty context: give at least one Condition to condition on")
        conditions = check_conditions(conditions, d)
        ph = np.array([[c.phase for c in conditions]], np.float32)
        mask = np.stack([c.mask() for c in conditions])[None]
        raw = np.array([[c.values for c in conditions]], np.float32)
        vals = np.nan_to_num((raw - self.sm_mean) / self.sm_std) * mask
        gamma = None
        if not self.config.task_dim and task_params is not None:
            raise ValueError("this model has no task parameters γ (it was fitted without task_params): drop "
                             "task_params, or fit a new CNMPModel with them")
        if self.config.task_dim:
            if task_params is None:
                raise ValueError(f"this model is conditioned on {self.config.task_dim} task parameters γ; give task_params")
            gp = np.asarray(task_params, np.float32).reshape(1, -1)
            if gp.shape[1] != self.config.task_dim or not np.isfinite(gp).all():
                raise ValueError(f"task_params must be {self.config.task_dim} finite values; got {gp}")
            gamma = torch.from_numpy(self._norm_task(gp)).to(self.device)
        t = lambda a: torch.from_numpy(a).to(self.device)  # noqa: E731
        return Context(t(ph), t(vals), t(mask), torch.ones(ph.shape, dtype=torch.bool, device=self.device), gamma)

    def _query(self, phases) -> torch.Tensor:
        return torch.from_numpy(query_phases(phases, np.float32)[None]).to(self.device)

    @torch.no_grad()
    def predict(self, phases, conditions: list[Condition], task_params=None, expert: int | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """Mean and σ of the SM at ``phases`` (values in [0, 1]) given the conditions: two ``[M, D]`` arrays.
        With a mixture (``n_experts`` K > 1): those of the most probable expert, or of expert ``expert``."""
        q = self._query(phases)
        ctx = self.context(conditions, task_params)
        if expert is None:
            mean, std = self.policy.model(ctx, q)
        else:
            k = n_experts(self.policy.model)
            if int(expert) != expert or not 0 <= expert < k:
                raise ValueError(f"expert must be an integer in 0..{k - 1} (this model has {k}), got {expert}")
            means, stds, _ = mixture_of(self.policy.model, ctx, q)
            mean, std = means[:, int(expert)], stds[:, int(expert)]
        mean = mean[0].cpu().numpy() * self.sm_std + self.sm_mean
        return mean, std[0].cpu().numpy() * self.sm_std

    @torch.no_grad()
    def predict_mixture(self, phases, conditions: list[Condition], task_params=None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every expert's prediction and probability given the conditions: μ_k and σ_k ``[K, M, D]`` (SM units)
        and the gate's π ``[K]`` (sums to 1). K = 1 (a plain CNMP): one expert of probability 1."""
        q, ctx = self._query(phases), self.context(conditions, task_params)
        means, stds, probs = mixture_of(self.policy.model, ctx, q)
        return (means[0].cpu().numpy() * self.sm_std + self.sm_mean, stds[0].cpu().numpy() * self.sm_std,
                probs[0].cpu().numpy())

    # ---- persistence ----------------------------------------------------------------------------------

    def save(self, path: str | Path) -> Path:
        """Write a LeRobot checkpoint: config.json, model.safetensors (with the normalization statistics) and the
        processors (identity normalizers)."""
        from lerobot_cnmp.policy.processor_cnmp import make_cnmp_pre_post_processors

        self._require_fitted()
        path = Path(path)
        self.policy.save_pretrained(path)
        pre, post = make_cnmp_pre_post_processors(self.config)
        pre.save_pretrained(path)
        post.save_pretrained(path)
        return path

    @classmethod
    def load(cls, path: str | Path, device: str = "cpu") -> CNMPModel:
        """Load a checkpoint written by ``save`` or by ``lerobot-train`` (its ``pretrained_model`` folder)."""
        policy, pre, _ = load_pretrained(path, device=device)
        if not policy.config.spec.tied:
            raise ValueError(f"the checkpoint at {path} models a joint SM ({', '.join(policy.config.sm_names or [])}); "
                             "CNMPModel takes tied SM trajectories: use load_pretrained(path) for it")
        model = cls(config=policy.config, device=device)
        model.policy = policy
        return model


def sm_stats(policy) -> dict:
    """The SM's (and γ's) normalization statistics a CNMP policy holds, as numpy arrays."""
    n = policy.normalizer
    out = {"sm": {"mean": n.sm_mean.cpu().numpy(), "std": n.sm_std.cpu().numpy()}}
    if policy.config.task_dim:
        out["task"] = {"mean": n.task_mean.cpu().numpy(), "std": n.task_std.cpu().numpy()}
    return out


def _check_local_checkpoint(path: str) -> None:
    """A local checkpoint folder holds a CNMP ``config.json`` and a whole ``model.safetensors``; a path that
    does not exist must be a Hub repo id. Each failure is an error naming the path."""
    from huggingface_hub.errors import HFValidationError
    from huggingface_hub.utils import validate_repo_id

    folder = Path(path)
    if not folder.exists():
        try:
            validate_repo_id(path)
        except HFValidationError:
            raise FileNotFoundError(f"no checkpoint at {path}: the folder does not exist (and {path!r} is not a "
                                    "Hub repo id either)") from None
        return  # a Hub repo id: from_pretrained fetches it
    cfg_file = folder / "config.json"
    if not cfg_file.is_file():
        hint = folder / "pretrained_model"
        more = f" (did you mean {hint}?)" if (hint / "config.json").is_file() else ""
        raise FileNotFoundError(f"no config.json in {path}: not a CNMP checkpoint folder{more}")
    try:
        kind = json.loads(cfg_file.read_text()).get("type")
    except (ValueError, AttributeError) as e:
        raise ValueError(f"{cfg_file} is not a JSON object ({e}): the checkpoint's config is damaged") from e
    if kind != "cnmp":
        raise ValueError(f"the checkpoint at {path} is a {kind!r} policy, not a 'cnmp' one")
    weights = folder / "model.safetensors"
    if not weights.is_file():
        raise FileNotFoundError(f"no model.safetensors in {path}: the checkpoint has no weights")


def load_pretrained(path: str | Path, device: str | None = None):
    """(policy, preprocessor, postprocessor) from a checkpoint folder or Hub repo id.

    Restores the checkpoint's own processors; the normalization statistics travel in the weights. Building processors
    from ``PreTrainedConfig.from_pretrained(path)`` alone would silently get empty statistics, because
    that config's ``pretrained_path`` stays None."""
    from lerobot.policies.factory import make_pre_post_processors

    path = str(path)
    _check_local_checkpoint(path)
    try:
        policy = CNMPPolicy.from_pretrained(path)
    except (FileNotFoundError, OSError) as e:
        if Path(path).exists():
            raise
        from huggingface_hub import constants

        offline = " (HF_HUB_OFFLINE=1)" if constants.HF_HUB_OFFLINE else ""
        raise FileNotFoundError(
            f"{path!r} is not a local checkpoint folder, and as a Hub repo id it could not be fetched: the Hub "
            f"is unreachable{offline} and the repo is not in the local cache ({type(e).__name__})"
        ) from e
    if device is not None:
        policy.config.device = device
        policy.to(device)
    overrides = {"device_processor": {"device": policy.config.device}}
    pre, post = make_pre_post_processors(
        policy.config, pretrained_path=path, preprocessor_overrides=overrides
    )
    if not policy.normalizer.ready:
        raise ValueError(f"the checkpoint at {path} has no SM normalization statistics")
    return policy, pre, post
