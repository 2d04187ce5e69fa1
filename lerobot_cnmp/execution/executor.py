"""The execution loop of a CNMP (paper Sec. III, Fig. 3), apart from the model and its training.

:class:`~lerobot_cnmp.execution.config.ExecutionConfig` (``--policy.execution.*``) holds every execution setting; :class:`CNMPExecutor` holds
the per-env execution state and runs the loop for :class:`~lerobot_cnmp.policy.modeling_cnmp.CNMPPolicy`, which
only forwards LeRobot's calls (``select_action``, ``predict_action_chunk``, ``reset``) to it.

Per env the executor keeps a phase τ (0 after ``reset``) that advances by Δ = 1 / (control_fps x
demo_duration_s) per control step. Each step it

1. holds τ while the tracking error exceeds ``phase_stop_threshold`` (with ``online_feedback``). The error is
   max over the tracked dims of |sensed SM - SM expected now| divided by the σ the CNMP predicted for that
   point (``phase_stop_units="sigma"``), so a near-constant dim, whose normalized value is noisy but whose
   predicted σ says so, does not stall the phase. A phase held for ``phase_stop_timeout_s`` seconds resumes
   anyway (a blocked robot does not freeze the movement forever; a warning is logged once per episode);
2. conditions on the episode's conditions -- the user's (:meth:`CNMPExecutor.set_conditions`,
   ``--policy.conditions``) and those an env writes in ``observation.environment_state`` slots -- on the
   sensed dims at the first step (t = 0, ``condition_on_start``) and, with ``online_feedback``, on the current
   sensed dims: at τ in the joint layout, at τ - Δ in the tied layout (the state the previous command reached);
3. outputs the predicted ``action`` dims at τ (joint layout), or the PD command s + kp·e + kd·(e - e_prev),
   e = μ(τ) - s (tied layout), in the dataset's units.

Chunks (:meth:`CNMPExecutor.chunk`, LeRobot's ``predict_action_chunk``) plan ``n_action_steps`` actions at
τ, τ + Δ, ...; the phase clock moves to the chunk's last step, so a caller that executes the chunk and asks
again continues where it ended. With RTC (``prev_chunk_left_over``) the new chunk starts at the phase of
the first leftover action and is conditioned on the leftover actions that run while it is computed
(``inference_delay``), at their own phases: the CNMP passes through them, so the boundary is continuous.

All predictions go through :meth:`CNMPExecutor.predict` (one call site: a mixture of CNMPs plugs in there).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from lerobot_cnmp.execution.config import ExecutionConfig
from lerobot_cnmp.execution.modes import ModeSelector

from lerobot.utils.constants import OBS_ENV_STATE

from lerobot_cnmp.execution.conditions import decode_conditions
from lerobot_cnmp.model.cnmp import Context
from lerobot_cnmp.model.mixture import MixtureCNMP, pick_expert


logger = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------------------
# Conditions from the user
# --------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class UserCondition:
    """One validated condition: SM ``values`` (dataset units) at ``phase``, on the SM dims ``mask`` marks."""

    phase: float
    values: np.ndarray  # [D], NaN outside the mask
    mask: np.ndarray  # [D] 0/1


def load_condition_spec(spec) -> list[dict]:
    """Conditions as a list of dicts from: a list/dict, a JSON string, or a path to a JSON/YAML file."""
    if spec is None:
        return []
    if isinstance(spec, (str, Path)):
        text = str(spec).strip()
        if not text:
            return []
        path = Path(text)
        if text[0] not in "[{" and path.suffix.lower() in (".json", ".yaml", ".yml"):
            if not path.is_file():
                raise FileNotFoundError(f"conditions file {path} does not exist")
            text = path.read_text()
            if path.suffix.lower() in (".yaml", ".yml"):
                import yaml

                spec = yaml.safe_load(text)
            else:
                spec = json.loads(text)
        else:
            # JSON, or YAML flow style (what draccus hands over from the command line: it parses a CLI value
            # as YAML and a str field gets the Python repr of the list)
            import yaml

            try:
                spec = yaml.safe_load(text)
            except yaml.YAMLError as e:
                raise ValueError(f"conditions {text!r} are neither JSON/YAML nor a path to a .json/.yaml file: {e}") from e
            if isinstance(spec, str):
                raise ValueError(f"conditions {text!r} are neither JSON/YAML nor a path to a .json/.yaml file (no such "
                                 "file)")
    if isinstance(spec, dict):
        spec = [spec]
    if not isinstance(spec, (list, tuple)) or not all(isinstance(c, dict) for c in spec):
        raise ValueError(f"conditions must be a dict or a list of dicts (e.g. [{{\"t\": 1.0, \"x\": 0.5}}]), got {spec!r}")
    return [dict(c) for c in spec]


def dim_lookup(spec, sm_names=None) -> dict[str, list[int]]:
    """Every name a user may give an SM dim: the dataset's dim name (all SM dims of that name, e.g. the state
    and the action of one joint), the SM's unique name (``state.x`` when the name repeats; ``sm_names``, saved
    in the checkpoint), ``feature:name`` and ``feature:index``."""
    short = {"observation.state": "state", "action": "action"}
    unique = list(sm_names) if sm_names is not None and len(sm_names) == spec.size else list(spec.names)
    out: dict[str, list[int]] = {}
    for i, (d, u) in enumerate(zip(spec.dims, unique, strict=True)):
        prefix = f"{short.get(d.feature, d.feature)}."
        bare = u[len(prefix):] if u.startswith(prefix) and u != d.name else u
        for key in {bare, u, f"{d.feature}:{bare}", d.key}:
            out.setdefault(key, [])
            if i not in out[key]:
                out[key].append(i)
    return out


def parse_conditions(raw, spec, demo_duration_s: float | None, capacity: int, sm_names=None) -> list[UserCondition]:
    """Validate user conditions against an SM: each has ``t`` (phase in [0, 1]) or ``time_s`` (seconds into
    the movement, / demo_duration_s) and values by dim name. Any error names the condition and the problem."""
    items = load_condition_spec(raw)
    if len(items) > capacity:
        raise ValueError(f"{len(items)} conditions given; this CNMP takes at most {capacity} (max_conditions)")
    names = dim_lookup(spec, sm_names)
    display = list(sm_names) if sm_names is not None and len(sm_names) == spec.size else spec.names
    out = []
    for k, item in enumerate(items):
        item = dict(item)
        if ("t" in item) == ("time_s" in item):
            raise ValueError(f"condition {k} {item}: give its time as exactly one of 't' (phase in [0, 1]) or "
                             "'time_s' (seconds from the movement's start)")
        if "t" in item:
            phase = _number(item.pop("t"), k, "t")
        else:
            seconds = _number(item.pop("time_s"), k, "time_s")
            if not demo_duration_s:
                raise ValueError(f"condition {k}: 'time_s' needs the demonstrations' duration (demo_duration_s), "
                                 "which this checkpoint does not have; give the phase 't'")
            phase = seconds / demo_duration_s
        if not 0.0 <= phase <= 1.0:
            raise ValueError(f"condition {k}: phase {phase:g} is outside [0, 1] (the movement lasts "
                             f"{demo_duration_s or '?'} s)")
        if not item:
            raise ValueError(f"condition {k} constrains no dim; give values by name, one of {sorted(names)}")
        values = np.full(spec.size, np.nan, dtype=np.float32)
        mask = np.zeros(spec.size, dtype=np.float32)
        for name, value in item.items():
            name = str(name)  # YAML reads a dim named 1 as an int
            if name not in names:
                raise ValueError(f"condition {k}: unknown dim {name!r}; the SM's dims are {sorted(names)}")
            v = _number(value, k, name)
            for i in names[name]:
                if mask[i] and values[i] != v:
                    raise ValueError(f"condition {k} gives SM dim {display[i]!r} two values")
                values[i], mask[i] = v, 1.0
        out.append(UserCondition(float(phase), values, mask))
    return out


def _number(value, k: int, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"condition {k}: {name!r} = {value!r} is not a number") from None
    if not math.isfinite(v):
        raise ValueError(f"condition {k}: {name!r} = {value!r} is NaN or infinite")
    return v


# --------------------------------------------------------------------------------------------------------
# The executor
# --------------------------------------------------------------------------------------------------------


class CNMPExecutor:
    """Per-env execution state and the execution loop of one CNMP policy.

    ``policy`` gives the pieces the loop needs and does not own: its ``config`` (SM spec, ``execution``,
    durations), ``normalizer`` (SM units), ``network()`` (the torch model or its numpy copy) and
    ``episode_inputs(batch)`` (γ and image embeddings)."""

    def __init__(self, policy):
        self.policy = policy
        self._user: list[UserCondition] = []
        self._user_tensors: tuple | None = None
        self._user_group: tuple | None = None  # (the _user_tensors it expands, n, the group of n envs)
        self._index_cache: dict = {}
        self._slots_cache: tuple | None = None
        self.reset()
        self.set_conditions(policy.config.conditions)

    # ---- settings ---------------------------------------------------------------------------------------

    @property
    def config(self):
        return self.policy.config

    @property
    def settings(self) -> ExecutionConfig:
        return self.policy.config.execution

    @property
    def control_fps(self) -> float:
        c = self.config
        return c.execution.control_fps or c.dataset_fps or 1.0

    @property
    def phase_step(self) -> float:
        c, e = self.config, self.settings
        if e.phase_step is not None:
            return e.phase_step
        if c.demo_duration_s is None:
            raise RuntimeError(
                "demo_duration_s is unknown: train on a dataset (it is set from the episodes' timestamps) or set "
                "--policy.demo_duration_s or --policy.execution.phase_step"
            )
        return min(1.0, 1.0 / (self.control_fps * c.demo_duration_s))

    # ---- state --------------------------------------------------------------------------------------------

    def reset(self) -> None:
        """Restart every env's execution state (the user's conditions stay)."""
        self.phase: Tensor | None = None  # τ per env: the phase of the last action emitted
        self.start: Tensor | None = None  # sensed SM at the first step (condition_on_start), normalized
        self.target: Tensor | None = None  # tied: SM commanded at the previous step (normalized)
        self.expected: Tensor | None = None  # joint: sensed SM predicted for this step (normalized)
        self.reference_std: Tensor | None = None  # σ of target / expected
        self.error: Tensor | None = None  # previous PD error e, for the D term
        self.inputs: Tensor | None = None  # γ and image embeddings read at the first step
        self.origin: Tensor | None = None  # raw γ of the task-frame dims at the first step (SM layout)
        self.has_inputs = False
        self.held_steps: Tensor | None = None  # consecutive steps the phase has been held, per env
        self.timed_out = False  # the phase-stop timeout fired in this episode (warning logged)
        self.last_chunk: Tensor | None = None  # the previous chunk (normalized SM means) and its phases
        self.last_chunk_actions: Tensor | None = None
        self.last_chunk_phase: Tensor | None = None
        self.last_chunk_step: int | None = None  # the caller's timestep of the last chunk's first action
        self.last_std: Tensor | None = None  # σ of the last action(s) returned, dataset units
        self._start_cache: tuple | None = None  # (start, its context point)
        self._static_cache: tuple | None = None  # (groups, their concatenation, every env has a valid point)
        c = self.config
        self.modes = ModeSelector(c.mode_switch_margin, c.expert_selection)  # which expert is followed (K > 1)

    def _ensure_state(self, batch: dict[str, Tensor]) -> int:
        ref = next((v for k, v in batch.items() if isinstance(v, Tensor) and k.startswith("observation.")), None)
        if ref is None:
            raise KeyError(f"the observation has no 'observation.*' tensor; it has {sorted(batch)}")
        n = ref.shape[0]
        if self.phase is None or self.phase.shape[0] != n:
            self.reset()
            self.phase = torch.zeros(n, device=ref.device, dtype=torch.float32)
            self.held_steps = torch.zeros(n, device=ref.device, dtype=torch.long)
        return n

    # ---- conditions -------------------------------------------------------------------------------------

    def set_conditions(self, conditions) -> None:
        """Set the user's conditions (a list of dicts, a dict, a JSON string or a .json/.yaml path; None or []
        clears them) for every env, in the dataset's units and dim names, e.g.
        ``[{"t": 1.0, "shoulder_pan.pos": 12.5, "gripper.pos": 0}]`` (``t``: phase; or ``time_s``: seconds).
        Validated at once (a bad condition raises before anything moves); the next step or chunk is planned
        with them (a goal that moves mid-episode: the executor re-plans from the current phase)."""
        c = self.config
        parsed = parse_conditions(conditions, c.spec, c.demo_duration_s, c.max_conditions, c.sm_names)
        if len(parsed) + c.env_condition_slots > c.max_conditions:
            raise ValueError(
                f"{len(parsed)} user conditions + {c.env_condition_slots} environment_state slots exceed this CNMP's "
                f"max_conditions={c.max_conditions}")
        self._user = parsed
        self._user_tensors = None

    @property
    def conditions(self) -> list[UserCondition]:
        return list(self._user)

    def _user_context(self, n: int, device) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
        if not self._user:
            return None
        key = self._normalizer_key()
        if self._user_tensors is None or self._user_tensors[0].device != torch.device(device) or \
                self._user_tensors[3] != key:
            norm = self.policy.normalizer
            norm.require()
            phase = torch.tensor([u.phase for u in self._user], dtype=torch.float32, device=device)
            raw = torch.from_numpy(np.stack([u.values for u in self._user])).to(device)
            mask = torch.from_numpy(np.stack([u.mask for u in self._user])).to(device)
            values = torch.where(mask > 0.5, norm.sm(torch.nan_to_num(raw)), torch.zeros_like(raw))
            self._user_tensors = (phase, values, mask, key)
        cached = self._user_group  # the batch-sized group, kept while the conditions and n stay
        if cached is None or cached[0] is not self._user_tensors or cached[1] != n:
            phase, values, mask, _ = self._user_tensors
            k = phase.shape[0]
            group = (phase[None].expand(n, k), values[None].expand(n, -1, -1), mask[None].expand(n, -1, -1),
                     torch.ones(n, k, dtype=torch.bool, device=device))
            self._user_group = cached = (self._user_tensors, n, group)
        return cached[2]

    def condition_slots(self, batch: dict[str, Tensor]):
        """The ``environment_state`` slots as context points (phase, normalized values, mask, valid); an env
        writes the same slots every step of an episode, so the last decoding is reused while they are equal."""
        env = batch[OBS_ENV_STATE]
        cached, key = self._slots_cache, self._normalizer_key()
        if cached is not None and cached[2] == key and cached[0].shape == env.shape and \
                cached[0].device == env.device and torch.equal(cached[0], env):
            return cached[1]
        out = self._decode_slots(env)
        self._slots_cache = (env.clone(), out, key)
        return out

    def _normalizer_key(self) -> tuple:
        """Changes whenever the SM statistics do (cached normalized conditions are then rebuilt)."""
        n = self.policy.normalizer
        return (n.sm_mean.data_ptr(), n.sm_mean._version, n.sm_std.data_ptr(), n.sm_std._version)

    def _decode_slots(self, env: Tensor):
        d = self.config.sm_dim
        present, c_phase, c_values, c_mask = decode_conditions(env, d)
        given = present > 0.5
        check_finite(OBS_ENV_STATE + " (flags, phases, masks)", torch.stack([present, c_phase], -1))
        used = given[..., None] & (c_mask > 0.5)
        if bool((~torch.isfinite(c_values) & used).any()):
            raise ValueError(f"a condition in {OBS_ENV_STATE} has NaN or infinite values in a constrained dim")
        if bool(((c_phase < 0) | (c_phase > 1))[given].any()):
            raise ValueError("a condition in environment_state has a phase outside [0, 1]")
        norm = self.policy.normalizer
        values = torch.where(used, norm.sm(torch.nan_to_num(c_values.float())), torch.zeros_like(c_values))
        return c_phase, values, c_mask.float(), given & (c_mask.sum(-1) > 0)

    # ---- sensing ------------------------------------------------------------------------------------------

    def dims_mask(self, like: Tensor, dims) -> Tensor:
        """A 0/1 mask shaped like ``like`` with ones at SM ``dims`` (None: all); built once per shape and device
        (read only: callers never write into it)."""
        key = ("mask", None if dims is None else tuple(dims), tuple(like.shape), like.device, like.dtype)
        mask = self._index_cache.get(key)
        if mask is None:
            if dims is None:
                mask = torch.ones_like(like)
            else:
                mask = torch.zeros_like(like)
                mask[..., list(dims)] = 1.0
            self._index_cache[key] = mask
        return mask

    def feedback_mask(self, like: Tensor) -> Tensor:
        """The fed-back dims: ``feedback_dims``, else every sensed dim."""
        spec, e = self.config.spec, self.settings
        dims = e.feedback_dims if e.feedback_dims is not None else (None if spec.tied else spec.sensed)
        return self.dims_mask(like, dims)

    def sensed_sm(self, batch: dict[str, Tensor]) -> Tensor | None:
        """The live observation's sensed dims as a normalized SM vector [B, D] (other dims 0)."""
        spec = self.config.spec
        out = None
        for feature, pairs in spec.sensed_features.items():
            if feature not in batch:
                raise KeyError(f"the CNMP feeds back {feature!r}: the observation needs it; it has {sorted(batch)}")
            x = batch[feature]
            x = x.reshape(x.shape[0], -1) if x.ndim != 2 else x
            top = self._index_cache.get(("top", feature))
            if top is None:
                top = self._index_cache[("top", feature)] = max(k for _, k in pairs)
            if x.shape[-1] <= top:
                raise ValueError(f"{feature!r} has {x.shape[-1]} dims, the SM reads dim {top} "
                                 f"of it (the checkpoint's SM does not match this env/robot)")
            if spec.tied and x.shape[-1] != spec.size:
                raise ValueError(f"{feature!r} has {x.shape[-1]} dims, the SM has {spec.size}")
            if len(spec.sensed_features) == 1 and x.shape[-1] == spec.size and self._identity(feature):
                out = x.float()  # the feature is the SM itself, dim for dim
                check_finite(feature, out)
                break
            if out is None:
                out = torch.zeros(x.shape[0], spec.size, dtype=torch.float32, device=x.device)
            key = (feature, x.device)
            if key not in self._index_cache:  # (SM index, feature index) tensors, built once per device
                self._index_cache[key] = (torch.tensor([i for i, _ in pairs], device=x.device),
                                          torch.tensor([k for _, k in pairs], device=x.device))
            idx, src = self._index_cache[key]
            vals = x[:, src].float()
            check_finite(feature, vals)
            out[:, idx] = vals
        if out is None:
            return None
        if spec.origins:  # task frames: minus the γ this episode started with
            if self.origin is None or self.origin.shape[0] != out.shape[0]:
                gamma = self.policy.task_params(batch)
                sm_idx, g_idx = zip(*spec.origins, strict=True)
                self.origin = torch.zeros_like(out)
                self.origin[:, list(sm_idx)] = gamma[:, list(g_idx)].to(out)
            out = out - self.origin
        full = self.policy.normalizer.sm(out)
        if spec.tied:  # every SM dim is sensed
            return full
        return full * self.dims_mask(full[0], spec.sensed)

    def _identity(self, feature: str) -> bool:
        """Whether ``feature``'s dim k is SM dim k for every SM dim (a state that is the SM)."""
        key = ("identity", feature)
        if key not in self._index_cache:
            pairs = self.config.spec.sensed_features[feature]
            self._index_cache[key] = sorted(pairs) == [(i, i) for i in range(self.config.spec.size)]
        return self._index_cache[key]

    # ---- context and prediction -----------------------------------------------------------------------------

    def execution_context(self, batch: dict[str, Tensor], phase: Tensor, sensed: Tensor | None = None,
                          extra: tuple[Tensor, Tensor, Tensor] | None = None) -> Context:
        """Conditions from ``environment_state`` slots, the user's conditions, the sensed dims at the first step
        at t = 0, (with ``online_feedback``) the current sensed dims (at τ, or τ - Δ in the tied layout), and
        ``extra`` points (phase [B, K], values [B, K, D], mask [B, K, D]; RTC's leftover actions)."""
        c, e = self.config, self.settings
        self.policy.normalizer.require()
        need_state = (e.online_feedback or e.condition_on_start) and bool(c.spec.sensed)
        if need_state and sensed is None:
            sensed = self.sensed_sm(batch)
        groups = []  # the points that stay while the episode runs: slots, the user's conditions, the start
        if c.env_condition_slots and OBS_ENV_STATE in batch:
            groups.append(self.condition_slots(batch))
        user = self._user_context(phase.shape[0], phase.device)
        if user is not None:
            groups.append(user)
        if e.condition_on_start and need_state:
            groups.append(self._start_point(sensed))
        static, static_covers_every_env = self._static_points(groups)
        dynamic = []
        if e.online_feedback and need_state:
            at = (phase - self.phase_step).clamp(min=0.0) if c.spec.tied else phase
            # at phase 0 the sensed state is the start itself: a second copy would double its weight in the
            # mean aggregation and pull the plan away from the other conditions
            fresh = at > 0 if e.condition_on_start else torch.ones_like(phase, dtype=torch.bool)
            dynamic.append((at[:, None], sensed[:, None, :], self.feedback_mask(sensed)[:, None, :], fresh[:, None]))
        if extra is not None:
            dynamic.append((extra[0], extra[1], extra[2], torch.ones_like(extra[0], dtype=torch.bool)))
        if static is None and not dynamic:
            raise ValueError(
                "nothing to condition on: no conditions (user or environment_state) and both online_feedback and "
                "condition_on_start are off"
            )
        parts = ([static] if static is not None else []) + dynamic
        pha, val, msk, valid = (torch.cat(x, 1) if len(parts) > 1 else x[0] for x in zip(*parts, strict=True))
        if not static_covers_every_env and not bool(valid.any(dim=1).all()):
            raise ValueError("an env in the batch has no condition to condition on (empty context)")
        if not self.has_inputs:
            self.inputs, self.has_inputs = self.policy.episode_inputs(batch), True
        return Context(pha, val, msk, valid, self.inputs)

    def _start_point(self, sensed: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The sensed SM at the episode's first step as a context point at t = 0 (kept for the episode)."""
        if self.start is None or self.start.shape[0] != sensed.shape[0]:
            self.start = sensed.clone()
        cached = self._start_cache
        if cached is None or cached[0] is not self.start:
            start = self.start
            mask = self.dims_mask(start[0], None if self.config.spec.tied else self.config.spec.sensed)
            n = start.shape[0]
            group = (torch.zeros(n, 1, device=start.device), start[:, None, :], mask.expand_as(start)[:, None, :],
                     torch.ones(n, 1, dtype=torch.bool, device=start.device))
            self._start_cache = cached = (start, group)
        return cached[1]

    def _static_points(self, groups: list[tuple]) -> tuple[tuple | None, bool]:
        """(the groups concatenated, whether every env has a valid point among them), rebuilt only when one of
        the groups is a new object (each group is itself cached while its source is unchanged); (None, False)
        without groups."""
        if not groups:
            return None, False
        cached = self._static_cache
        if cached is None or len(cached[0]) != len(groups) or any(a is not b for a, b in zip(cached[0], groups)):
            joined = tuple(torch.cat(x, 1) if len(groups) > 1 else x[0] for x in zip(*groups, strict=True))
            self._static_cache = cached = (list(groups), joined, bool(joined[3].any(dim=1).all()))
        return cached[1], cached[2]

    def predict(self, context: Context, queries: Tensor) -> tuple[Tensor, Tensor]:
        """(μ, σ) of the SM at ``queries`` [B, M] given ``context`` (normalized units), [B, M, D] each. The one
        place execution calls the network."""
        model = self.policy.model
        if not isinstance(model, MixtureCNMP):
            return self.policy.network()(context, queries)
        means, stds, probs = model.mixture(context, queries)
        return pick_expert(means, stds, self.modes(probs))

    # ---- the loop's pieces ----------------------------------------------------------------------------------

    def tracking_error(self, sensed: Tensor) -> Tensor:
        """Per env, max over the tracked dims (``tracking_dims``, else the fed-back ones) of |sensed SM - SM
        expected now| (tied: the SM commanded at the previous step), in ``phase_stop_units``."""
        spec, e = self.config.spec, self.settings
        ref = self.target if spec.tied else self.expected
        if ref is None:
            return torch.zeros(sensed.shape[0], device=sensed.device, dtype=sensed.dtype)
        dims = e.tracking_dims if e.tracking_dims is not None else e.feedback_dims
        mask = self.dims_mask(sensed, dims) if dims is not None else self.feedback_mask(sensed)
        err = (sensed - ref).abs()
        if e.phase_stop_units == "sigma" and self.reference_std is not None:
            err = err / self.reference_std
        return (err * mask).amax(dim=-1)

    def pd_gains(self, std: Tensor) -> tuple[Tensor, Tensor]:
        """(kp, kd) per env and SM dim: kp constant or scaled by sigma_ref / σ within [kp_min, kp_max]; outside
        ``pd_dims`` kp = 1 and kd = 0 (the prediction itself is commanded)."""
        e = self.settings
        kp = torch.full_like(std, e.pd_kp) if not e.sigma_scaled_gains else (e.pd_kp * e.sigma_ref / std).clamp(
            e.kp_min, e.kp_max)
        kd = torch.full_like(std, e.pd_kd)
        if e.pd_dims is not None:
            on = self.dims_mask(std, e.pd_dims)
            kp, kd = on * kp + (1 - on), on * kd
        return kp, kd

    def advance(self, sensed: Tensor | None) -> None:
        """Move τ one step on, except where the tracking error holds it (up to the timeout)."""
        e = self.settings
        if self.target is None and self.expected is None:  # the first step of an episode is at τ = 0
            return
        advance = None  # every env advances
        if e.online_feedback and e.phase_stop_threshold is not None and sensed is not None:
            ok = self.tracking_error(sensed) <= e.phase_stop_threshold
            if bool(ok.all()):  # the common case, in fewer ops: nothing held
                self.held_steps = torch.zeros_like(self.held_steps)
            else:
                self.held_steps = (self.held_steps + 1) * ~ok
                advance = ok
                if e.phase_stop_timeout_s is not None:
                    limit = max(1, math.ceil(e.phase_stop_timeout_s * self.control_fps))
                    forced = self.held_steps > limit
                    if bool(forced.any()) and not self.timed_out:
                        self.timed_out = True
                        logger.warning(
                            "CNMP: the tracking error has held the phase for more than %.2f s (phase_stop_timeout_s) "
                            "in env(s) %s; the phase advances again (is the robot blocked?)",
                            e.phase_stop_timeout_s, torch.nonzero(forced).flatten().tolist())
                    advance = advance | forced
        moved = (self.phase + self.phase_step).clamp(max=1.0)
        self.phase = moved if advance is None else torch.where(advance, moved, self.phase)

    # ---- LeRobot's calls ------------------------------------------------------------------------------------

    @torch.no_grad()
    def step(self, batch: dict[str, Tensor]) -> Tensor:
        """One step of the loop for every env of the batch: the action [B, A] in the dataset's units."""
        c, e = self.config, self.settings
        spec, norm = c.spec, self.policy.normalizer
        self._ensure_state(batch)
        norm.require()
        sensed = self.sensed_sm(batch) if spec.sensed else None
        self.advance(sensed)
        self.last_chunk = None
        if spec.tied:
            mean, std = self.predict(self.execution_context(batch, self.phase, sensed), self.phase[:, None])
            target, std = mean[:, 0], std[:, 0]
            action = target
            if e.online_feedback and sensed is not None:
                error = target - sensed
                previous = self.error if self.error is not None else error
                kp, kd = self.pd_gains(std)
                action = sensed + kp * error + kd * (error - previous)
                self.error = error
            self.target, self.reference_std = target, std
            self.last_std = std * norm.sm_std
            return norm.sm_inverse(action)
        nxt = (self.phase + self.phase_step).clamp(max=1.0)
        mean, std = self.predict(self.execution_context(batch, self.phase, sensed), torch.stack([self.phase, nxt], 1))
        self.expected, self.reference_std = mean[:, 1], std[:, 1]
        self.last_std = std[:, 0, spec.commanded] * norm.sm_std[spec.commanded]
        return norm.sm_inverse(mean[:, 0, spec.commanded], spec.commanded)

    def _leftover_phases(self, left: Tensor) -> Tensor | None:
        """[L] phases of RTC's leftover actions [L, A] (dataset units), found in the previous chunk: they are its
        rows from some offset on. None when they are not (another producer, or no previous chunk)."""
        prev, prev_phase = self.last_chunk_actions, self.last_chunk_phase
        nonzero = torch.nonzero(left.abs().amax(dim=-1) > 0).flatten()  # the engine pads with zero rows
        left = left[: int(nonzero[-1]) + 1] if nonzero.numel() else left[:0]
        if prev is None or left.shape[0] == 0:
            return None
        n = prev.shape[0]
        for j in range(n):
            m = min(left.shape[0], n - j)
            if torch.allclose(prev[j:j + m], left[:m].to(prev), atol=1e-6, rtol=0):
                return prev_phase[j:j + m]
        return None

    def _phase_of_step(self, step: int) -> Tensor | None:
        """The phase of control step ``step`` (a caller's timestep, e.g. the async client's) from the chunk the
        previous call planned for its own timestep; None without one."""
        if self.last_chunk_step is None or self.last_chunk_phase is None:
            return None
        k = step - self.last_chunk_step
        if k < 0:
            return None
        n = self.last_chunk_phase.shape[0]
        if k < n:
            return self.last_chunk_phase[k].reshape(1)
        return (self.last_chunk_phase[-1] + (k - n + 1) * self.phase_step).clamp(max=1.0).reshape(1)

    @torch.no_grad()
    def chunk(self, batch: dict[str, Tensor], n_steps: int | None = None, inference_delay: int = 0,
              prev_chunk_left_over: Tensor | None = None, timestep: int | None = None) -> tuple[Tensor, Tensor]:
        """The planned actions and their σ [B, n, A] (dataset units) at τ, τ + Δ, ... (see the module doc).
        ``timestep``: the caller's index of the control step the observation was taken at (LeRobot's async
        client numbers its observations); the chunk then starts at that step's phase in the previous plan."""
        c, e = self.config, self.settings
        spec, norm = c.spec, self.policy.normalizer
        n_steps = int(n_steps or e.n_action_steps)
        self._ensure_state(batch)
        norm.require()
        sensed = self.sensed_sm(batch) if spec.sensed else None
        step = self.phase_step
        extra = None
        start = None
        if prev_chunk_left_over is not None:
            left = prev_chunk_left_over
            left = left[0] if left.ndim == 3 else left
            if left.shape[0] and left.shape[-1] != spec.action_dim:
                raise ValueError(f"prev_chunk_left_over has {left.shape[-1]} action dims, the CNMP commands "
                                 f"{spec.action_dim}")
            phases = self._leftover_phases(left) if self.phase.shape[0] == 1 else None
            if phases is not None:
                start = phases[0].reshape(1)
                k = min(max(int(inference_delay), 1), phases.shape[0])  # the actions run while this chunk is made
                raw = torch.zeros(1, k, spec.size, device=self.phase.device)
                raw[0, :, spec.commanded] = left[:k].to(raw)
                mask = torch.zeros_like(raw)
                mask[..., spec.commanded] = 1.0
                values = norm.sm(raw) * mask
                extra = (phases[:k].reshape(1, k).to(raw), values, mask)
        if start is None and timestep is not None and self.phase.shape[0] == 1:
            start = self._phase_of_step(int(timestep))
        if start is None:
            self.advance(sensed)
            start = self.phase
        queries = (start[:, None] + step * torch.arange(n_steps + (0 if spec.tied else 1), device=start.device,
                                                        dtype=start.dtype)[None]).clamp(max=1.0)
        self.phase = start
        mean, std = self.predict(self.execution_context(batch, start, sensed, extra), queries)
        cmd = spec.commanded
        actions = norm.sm_inverse(mean[:, :n_steps, cmd], cmd)
        sigma = std[:, :n_steps, cmd] * norm.sm_std[cmd]
        # the clock: the chunk's last step was emitted
        self.phase = queries[:, n_steps - 1]
        if spec.tied:
            self.target, self.reference_std, self.error = mean[:, n_steps - 1], std[:, n_steps - 1], None
        else:
            self.expected, self.reference_std = mean[:, n_steps], std[:, n_steps]
        self.last_chunk_actions, self.last_chunk_phase = actions[0].clone(), queries[0, :n_steps].clone()
        self.last_chunk_step = None if timestep is None else int(timestep)
        self.last_chunk = mean
        self.last_std = sigma
        return actions, sigma


def check_finite(name: str, x: Tensor) -> None:
    # one reduction instead of isfinite + all: a NaN or ±inf anywhere makes the sum non-finite (so would values
    # near float32's limit, which no robot sends)
    if not math.isfinite(float(x.sum())):
        raise ValueError(f"{name} contains NaN or infinite values")

