"""The execution loop of a CNMP (paper Sec. III, Fig. 3), apart from the model and its training.

:class:`CNMPExecutor` is given what it runs -- the network (a zero-arg callable returning the current one: the
torch model or its numpy twin), the SM normalizer, the SM spec, the settings
(:class:`~lerobot_cnmp.execution.config.ExecutionConfig`, ``--policy.execution.*``, plus the trained movement's
facts, :class:`MovementFacts`) and a callable computing the episode-level input (γ and image embeddings) -- and
holds the per-env execution state. The policy only forwards LeRobot's calls (``select_action``,
``predict_action_chunk``, ``reset``) to it.

Per env the executor keeps a phase τ (0 after ``reset``) that advances by Δ = 1 / (control_fps x
demo_duration_s) per control step. Each step it

1. holds τ while the tracking error exceeds ``phase_stop_threshold`` (with ``online_feedback``). The error is
   max over the tracked dims of |sensed SM - SM expected now| divided by the σ the CNMP predicted for that
   point (``phase_stop_units="sigma"``), so a near-constant dim, whose normalized value is noisy but whose
   predicted σ says so, does not stall the phase. A phase held for ``phase_stop_timeout_s`` seconds resumes
   anyway (a blocked robot does not freeze the movement forever; a warning is logged once per episode);
   (:mod:`lerobot_cnmp.execution.feedback`)
2. conditions on the episode's conditions -- the user's (:meth:`CNMPExecutor.set_conditions`,
   ``--policy.conditions``) and those an env writes in ``observation.environment_state`` slots -- on the
   sensed dims at the first step (t = 0, ``condition_on_start``) and, with ``online_feedback``, on the current
   sensed dims: at τ in the joint layout, at τ - Δ in the tied layout (the state the previous command reached);
   (:mod:`lerobot_cnmp.execution.points`, :mod:`lerobot_cnmp.execution.sensing`)
3. outputs the predicted ``action`` dims at τ (joint layout), or the PD command s + kp·e + kd·(e - e_prev),
   e = μ(τ) - s (tied layout), in the dataset's units.

Chunks (:meth:`CNMPExecutor.chunk`, LeRobot's ``predict_action_chunk``) plan ``n_action_steps`` actions at
τ, τ + Δ, ...; the phase clock moves to the chunk's last step, so a caller that executes the chunk and asks
again continues where it ended. With RTC (``prev_chunk_left_over``) the new chunk starts at the phase of
the first leftover action and is conditioned on the leftover actions that run while it is computed
(``inference_delay``), at their own phases: the CNMP passes through them, so the boundary is continuous.

All predictions go through :meth:`CNMPExecutor.predict` (one call site: with a mixture of CNMPs the
:class:`~lerobot_cnmp.execution.modes.ModeSelector` picks the followed expert there).
"""

from __future__ import annotations

import logging
from typing import Any, Callable, Protocol

import torch
from torch import Tensor

from lerobot.utils.constants import OBS_ENV_STATE

from lerobot_cnmp.execution import feedback
from lerobot_cnmp.execution.conditions import Condition, parse_conditions
from lerobot_cnmp.execution.config import ExecutionConfig
from lerobot_cnmp.execution.modes import ModeSelector
from lerobot_cnmp.execution.points import ContextPoints
from lerobot_cnmp.execution.sensing import Sensing, check_finite  # noqa: F401  (check_finite: re-exported)
from lerobot_cnmp.model.cnmp import Context
from lerobot_cnmp.model.mixture import pick_expert

logger = logging.getLogger(__name__)


class MovementFacts(Protocol):
    """What execution needs to know of the trained CNMP besides its network, read when used (the policy
    learns ``demo_duration_s`` and ``dataset_fps`` from a dataset after it builds the executor)."""

    demo_duration_s: float | None  # the demonstrations' median duration: the phase's pace
    dataset_fps: float | None  # the demonstrations' rate: the control rate when execution.control_fps is None
    max_conditions: int  # the context points the CNMP takes (user conditions + environment_state slots)
    env_condition_slots: int  # the condition slots of observation.environment_state
    sm_names: tuple[str, ...] | None  # unique SM dim names (the user's conditions name dims by them)


class CNMPExecutor:
    """Per-env execution state and the execution loop of one CNMP.

    Args:
        network: zero-arg callable returning the network to run now: called as ``net(context, queries)`` ->
            (μ, σ); with ``modes`` (a mixture) ``net.mixture(context, queries)`` -> (μ_k, σ_k, π).
        normalizer: the SM statistics (``sm``, ``sm_inverse``, ``sm_std``, ``task``, ``require``).
        spec: the SM spec (:class:`~lerobot_cnmp.data.sm_spec.SMSpec`).
        settings: the execution settings, read when used (changing a field applies at the next step).
        movement: the trained movement's facts (:class:`MovementFacts`).
        episode_inputs: batch -> the episode-level input of the network (γ and image embeddings) or None.
        task_params: batch -> raw γ [B, G] (the task-frame origins of SM dims declared in the frame of γ).
        modes: the expert rule of a mixture CNMP; None for a single CNMP.
        conditions: the user's initial conditions (see :meth:`set_conditions`).
        feature_widths: dims of each observation feature the CNMP was trained on (checked when sensed).
    """

    def __init__(self, network: Callable[[], Any], normalizer, spec, settings: ExecutionConfig,
                 movement: MovementFacts, episode_inputs: Callable[[dict], Tensor | None],
                 task_params: Callable[[dict], Tensor | None], modes: ModeSelector | None = None,
                 conditions=None, feature_widths: dict[str, int] | None = None):
        self.network, self.normalizer, self.spec = network, normalizer, spec
        self.settings, self.movement = settings, movement
        self.episode_inputs, self.modes = episode_inputs, modes
        self.sensing = Sensing(spec, normalizer, feature_widths, task_params)
        self.points = ContextPoints(normalizer, spec.size)
        self.reset()
        self.set_conditions(conditions)

    # ---- settings ---------------------------------------------------------------------------------------

    @property
    def control_fps(self) -> float:
        return self.settings.control_fps or self.movement.dataset_fps or 1.0

    @property
    def phase_step(self) -> float:
        e = self.settings
        if e.phase_step is not None:
            return e.phase_step
        duration = self.movement.demo_duration_s
        if duration is None:
            raise RuntimeError(
                "demo_duration_s is unknown: train on a dataset (it is set from the episodes' timestamps) or set "
                "--policy.demo_duration_s or --policy.execution.phase_step"
            )
        return min(1.0, 1.0 / (self.control_fps * duration))

    # ---- state --------------------------------------------------------------------------------------------

    def reset(self) -> None:
        """Restart every env's execution state (the user's conditions stay)."""
        self.phase: Tensor | None = None  # τ per env: the phase of the last action emitted
        self.target: Tensor | None = None  # tied: SM commanded at the previous step (normalized)
        self.expected: Tensor | None = None  # joint: sensed SM predicted for this step (normalized)
        self.reference_std: Tensor | None = None  # σ of target / expected
        self.error: Tensor | None = None  # previous PD error e, for the D term
        self.inputs: Tensor | None = None  # γ and image embeddings read at the first step
        self.has_inputs = False
        self.held_steps: Tensor | None = None  # consecutive steps the phase has been held, per env
        self.timed_out = False  # the phase-stop timeout fired in this episode (warning logged)
        self.last_chunk: Tensor | None = None  # the previous chunk (normalized SM means) and its phases
        self.last_chunk_actions: Tensor | None = None
        self.last_chunk_phase: Tensor | None = None
        self.last_chunk_step: int | None = None  # the caller's timestep of the last chunk's first action
        self.last_std: Tensor | None = None  # σ of the last action(s) returned, dataset units
        self.points.reset()
        self.sensing.reset()
        if self.modes is not None:
            self.modes.reset()  # which expert is followed (K > 1)

    @property
    def start(self) -> Tensor | None:
        """The sensed SM at the episode's first step (normalized), kept as a condition at t = 0."""
        return self.points.start

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
        """Set the user's conditions (a list of dicts or :class:`Condition` objects, a dict, a JSON string or a
        .json/.yaml path; None or [] clears them) for every env, in the dataset's units and dim names, e.g.
        ``[{"t": 1.0, "shoulder_pan.pos": 12.5, "gripper.pos": 0}]`` (``t``: phase; or ``time_s``: seconds).
        Validated at once (a bad condition raises before anything moves); the next step or chunk is planned
        with them (a goal that moves mid-episode: the executor re-plans from the current phase)."""
        m = self.movement
        parsed = parse_conditions(conditions, self.spec, m.demo_duration_s, m.max_conditions, m.sm_names)
        if len(parsed) + m.env_condition_slots > m.max_conditions:
            raise ValueError(
                f"{len(parsed)} user conditions + {m.env_condition_slots} environment_state slots exceed this CNMP's "
                f"max_conditions={m.max_conditions}")
        self.points.set_user(parsed)

    @property
    def conditions(self) -> list[Condition]:
        return list(self.points.user)

    # ---- sensing ------------------------------------------------------------------------------------------

    def sensed_sm(self, batch: dict[str, Tensor]) -> Tensor | None:
        """The live observation's sensed dims as a normalized SM vector [B, D] (other dims 0)."""
        return self.sensing.sensed_sm(batch)

    def dims_mask(self, like: Tensor, dims) -> Tensor:
        return self.sensing.dims_mask(like, dims)

    def feedback_mask(self, like: Tensor) -> Tensor:
        """The fed-back dims: ``feedback_dims``, else every sensed dim."""
        spec, e = self.spec, self.settings
        dims = e.feedback_dims if e.feedback_dims is not None else (None if spec.tied else spec.sensed)
        return self.dims_mask(like, dims)

    # ---- context and prediction -----------------------------------------------------------------------------

    def execution_context(self, batch: dict[str, Tensor], phase: Tensor, sensed: Tensor | None = None,
                          extra: tuple[Tensor, Tensor, Tensor] | None = None) -> Context:
        """Conditions from ``environment_state`` slots, the user's conditions, the sensed dims at the first step
        at t = 0, (with ``online_feedback``) the current sensed dims (at τ, or τ - Δ in the tied layout), and
        ``extra`` points (phase [B, K], values [B, K, D], mask [B, K, D]; RTC's leftover actions)."""
        spec, e, points = self.spec, self.settings, self.points
        self.normalizer.require()
        need_state = (e.online_feedback or e.condition_on_start) and bool(spec.sensed)
        if need_state and sensed is None:
            sensed = self.sensed_sm(batch)
        groups = []  # the points that stay while the episode runs: slots, the user's conditions, the start
        if self.movement.env_condition_slots and OBS_ENV_STATE in batch:
            groups.append(points.slot_points(batch[OBS_ENV_STATE]))
        user = points.user_points(phase.shape[0], phase.device)
        if user is not None:
            groups.append(user)
        if e.condition_on_start and need_state:
            groups.append(points.start_point(sensed, self.dims_mask(sensed[0], None if spec.tied else spec.sensed)))
        static, static_covers_every_env = points.static(groups)
        dynamic = []
        if e.online_feedback and need_state:
            at = (phase - self.phase_step).clamp(min=0.0) if spec.tied else phase
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
            self.inputs, self.has_inputs = self.episode_inputs(batch), True
        return Context(pha, val, msk, valid, self.inputs)

    def predict(self, context: Context, queries: Tensor) -> tuple[Tensor, Tensor]:
        """(μ, σ) of the SM at ``queries`` [B, M] given ``context`` (normalized units), [B, M, D] each. The one
        place execution calls the network."""
        if self.modes is None:
            return self.network()(context, queries)
        means, stds, probs = self.network().mixture(context, queries)
        return pick_expert(means, stds, self.modes(probs))

    # ---- the loop's pieces ----------------------------------------------------------------------------------

    def tracking_error(self, sensed: Tensor) -> Tensor:
        """Per env, max over the tracked dims (``tracking_dims``, else the fed-back ones) of |sensed SM - SM
        expected now| (tied: the SM commanded at the previous step), in ``phase_stop_units``."""
        e = self.settings
        ref = self.target if self.spec.tied else self.expected
        if ref is None:
            return torch.zeros(sensed.shape[0], device=sensed.device, dtype=sensed.dtype)
        dims = e.tracking_dims if e.tracking_dims is not None else e.feedback_dims
        mask = self.dims_mask(sensed, dims) if dims is not None else self.feedback_mask(sensed)
        return feedback.tracking_error(sensed, ref, self.reference_std, mask, e.phase_stop_units)

    def pd_gains(self, std: Tensor) -> tuple[Tensor, Tensor]:
        """(kp, kd) per env and SM dim (:func:`lerobot_cnmp.execution.feedback.pd_gains`)."""
        pd_dims = self.settings.pd_dims
        return feedback.pd_gains(std, self.settings, None if pd_dims is None else self.dims_mask(std, pd_dims))

    def advance(self, sensed: Tensor | None) -> None:
        """Move τ one step on, except where the tracking error holds it (up to the timeout)."""
        e = self.settings
        if self.target is None and self.expected is None:  # the first step of an episode is at τ = 0
            return
        ok = None  # every env advances
        if e.online_feedback and e.phase_stop_threshold is not None and sensed is not None:
            ok = self.tracking_error(sensed) <= e.phase_stop_threshold
        limit = feedback.hold_limit_steps(e, self.control_fps)
        self.phase, self.held_steps, forced = feedback.advance_phase(self.phase, self.phase_step, ok,
                                                                     self.held_steps, limit)
        if forced is not None and bool(forced.any()) and not self.timed_out:
            self.timed_out = True
            logger.warning(
                "CNMP: the tracking error has held the phase for more than %.2f s (phase_stop_timeout_s) "
                "in env(s) %s; the phase advances again (is the robot blocked?)",
                e.phase_stop_timeout_s, torch.nonzero(forced).flatten().tolist())

    # ---- LeRobot's calls ------------------------------------------------------------------------------------

    @torch.no_grad()
    def step(self, batch: dict[str, Tensor]) -> Tensor:
        """One step of the loop for every env of the batch: the action [B, A] in the dataset's units."""
        e, spec, norm = self.settings, self.spec, self.normalizer
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
                kp, kd = self.pd_gains(std)
                action, self.error = feedback.pd_command(sensed, target, self.error, kp, kd)
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
        e, spec, norm = self.settings, self.spec, self.normalizer
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
