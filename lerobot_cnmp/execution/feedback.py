"""The feedback laws of execution (paper Sec. III, Fig. 3), as functions of tensors and the settings.

* the tracking error that stops the phase: max over the tracked dims of |sensed SM - reference|, divided by
  the σ predicted for the reference (``phase_stop_units="sigma"``) or in normalized units;
* the phase clock: τ advances by Δ per control step, except where the error exceeds
  ``phase_stop_threshold``; a phase held longer than ``phase_stop_timeout_s`` advances anyway;
* the PD law of the tied layout: a = s + kp·e + kd·(e - e_prev), e = μ(τ) - s, with kp constant or scaled by
  sigma_ref / σ within [kp_min, kp_max].
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from lerobot_cnmp.execution.config import ExecutionConfig


def tracking_error(sensed: Tensor, reference: Tensor, reference_std: Tensor | None, mask: Tensor,
                   units: str) -> Tensor:
    """Per env, max over the dims ``mask`` marks of |sensed - reference| (normalized SM), in ``units``."""
    err = (sensed - reference).abs()
    if units == "sigma" and reference_std is not None:
        err = err / reference_std
    return (err * mask).amax(dim=-1)


def pd_gains(std: Tensor, e: ExecutionConfig, pd_mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """(kp, kd) per env and SM dim for the predicted σ ``std``; outside ``pd_mask`` (None: every dim is PD
    tracked) kp = 1 and kd = 0: the prediction itself is commanded."""
    kp = torch.full_like(std, e.pd_kp) if not e.sigma_scaled_gains else (e.pd_kp * e.sigma_ref / std).clamp(
        e.kp_min, e.kp_max)
    kd = torch.full_like(std, e.pd_kd)
    if pd_mask is not None:
        kp, kd = pd_mask * kp + (1 - pd_mask), pd_mask * kd
    return kp, kd


def pd_command(sensed: Tensor, target: Tensor, previous_error: Tensor | None, kp: Tensor, kd: Tensor
               ) -> tuple[Tensor, Tensor]:
    """(the command s + kp·e + kd·(e - e_prev), the error e = target - s); without a previous error the D
    term is 0."""
    error = target - sensed
    previous = previous_error if previous_error is not None else error
    return sensed + kp * error + kd * (error - previous), error


def hold_limit_steps(e: ExecutionConfig, control_fps: float) -> int | None:
    """Control steps a phase may stay held (``phase_stop_timeout_s``), at least 1; None: forever."""
    return None if e.phase_stop_timeout_s is None else max(1, math.ceil(e.phase_stop_timeout_s * control_fps))


def advance_phase(phase: Tensor, step: float, ok: Tensor | None, held_steps: Tensor, limit: int | None
                  ) -> tuple[Tensor, Tensor, Tensor | None]:
    """The phase clock's move: (new phase, new held-step counts, the envs whose timeout released them now or
    None). ``ok``: per env, whether the tracking error allows advancing (None: every env advances)."""
    forced = None
    advance = None
    if ok is not None:
        if bool(ok.all()):  # the common case, in fewer ops: nothing held
            held_steps = torch.zeros_like(held_steps)
        else:
            held_steps = (held_steps + 1) * ~ok
            advance = ok
            if limit is not None:
                forced = held_steps > limit
                advance = advance | forced
    moved = (phase + step).clamp(max=1.0)
    return (moved if advance is None else torch.where(advance, moved, phase)), held_steps, forced
