"""Execution settings of a CNMP (``--policy.execution.<field>``): the phase clock, feedback, phase stopping,
PD tracking and chunking. None of them changes the model or its training."""

from __future__ import annotations

from dataclasses import dataclass

PHASE_STOP_UNITS = ("sigma", "normalized")


@dataclass
class ExecutionConfig:
    """How a CNMP is executed (``--policy.execution.<field>``); none of it changes the model or its training.

    Args:
        control_fps: The rate at which execution is called (``select_action`` per second). None: the
            dataset's fps. The phase advances by 1 / (control_fps x demo_duration_s) per step, so a robot
            controlled at another rate than the recording runs the movement in the same time.
        phase_step: Phase advance per control step; None: 1 / (control_fps x demo_duration_s).
        online_feedback: The paper's loop: every step, condition on the current sensed SM (``feedback_dims``)
            besides the episode's conditions, track the prediction with the PD law, and stop the phase while
            the tracking error is large. False: replay the trajectory generated at t = 0 (open loop).
        condition_on_start: Keep the state sensed at the first step after ``reset()`` as a condition at
            t = 0 for the whole episode (the start of the movement, as in the paper's Fig. 2).
        feedback_dims: SM dimensions fed back (conditioned on); None: every sensed dim.
        tracking_dims: SM dimensions of the tracking error that stops the phase; None: ``feedback_dims``.
        phase_stop_threshold: The phase does not advance while the tracking error exceeds this. None: never
            stop.
        phase_stop_units: ``"sigma"``: the error of each dim is divided by the σ predicted for the point it is
            compared with (the threshold is then a number of σ). ``"normalized"``: in units of the
            demonstrations' per-dim standard deviation (checkpoints written before the executor had its own
            config load with this, their threshold being in these units).
        phase_stop_timeout_s: Seconds a phase may stay held (consecutive control steps x 1 / control_fps);
            after that it advances again at the normal pace, whatever the error, until the error falls below
            the threshold and the count restarts. A warning is logged once per episode. None: hold forever.
        pd_kp, pd_kd: PD law on the position target (tied layout; the joint layout outputs the predicted action
            itself): action = s + kp·e + kd·(e - e_prev), e = μ(τ) - s.
        pd_dims: SM dimensions the PD law applies to; the others are commanded μ(τ) itself. None: all.
        sigma_scaled_gains: Scale kp per dim by sigma_ref / σ, clipped to [kp_min, kp_max].
        numpy_execution: On CPU, run the network through its numpy copy (``NumpyCNMP``: same weights and
            equations, 2-4x less time per control step than torch's per-op dispatch).
        n_action_steps: Actions per chunk of ``predict_action_chunk`` (LeRobot's queue-based callers, RTC,
            the async policy server).
    """

    control_fps: float | None = None
    phase_step: float | None = None
    online_feedback: bool = True
    condition_on_start: bool = True
    feedback_dims: tuple[int, ...] | None = None
    tracking_dims: tuple[int, ...] | None = None
    phase_stop_threshold: float | None = 3.0
    phase_stop_units: str = "sigma"
    phase_stop_timeout_s: float | None = 2.0
    pd_kp: float = 1.0
    pd_kd: float = 0.0
    pd_dims: tuple[int, ...] | None = None
    sigma_scaled_gains: bool = False
    sigma_ref: float = 0.05
    kp_min: float = 0.2
    kp_max: float = 1.0
    numpy_execution: bool = True
    n_action_steps: int = 50

    def __post_init__(self):
        if self.control_fps is not None and not self.control_fps > 0:
            raise ValueError(f"control_fps must be > 0, got {self.control_fps}")
        if self.phase_step is not None and not 0.0 < self.phase_step <= 1.0:
            raise ValueError(f"phase_step must be in (0, 1], got {self.phase_step}")
        if self.phase_stop_threshold is not None and not self.phase_stop_threshold > 0:
            raise ValueError(f"phase_stop_threshold must be > 0 (or None to never stop), got {self.phase_stop_threshold}")
        if self.phase_stop_units not in PHASE_STOP_UNITS:
            raise ValueError(f"phase_stop_units must be one of {PHASE_STOP_UNITS}, got {self.phase_stop_units!r}")
        if self.phase_stop_timeout_s is not None and not self.phase_stop_timeout_s > 0:
            raise ValueError(f"phase_stop_timeout_s must be > 0 (or None), got {self.phase_stop_timeout_s}")
        if not self.pd_kp > 0 or self.pd_kd < 0:
            raise ValueError(f"PD gains need pd_kp > 0 and pd_kd >= 0, got pd_kp={self.pd_kp}, pd_kd={self.pd_kd}")
        if not 0 < self.kp_min <= self.kp_max or not self.sigma_ref > 0:
            raise ValueError(
                f"need 0 < kp_min <= kp_max and sigma_ref > 0, got kp_min={self.kp_min}, kp_max={self.kp_max}, "
                f"sigma_ref={self.sigma_ref}"
            )
        for name in ("feedback_dims", "tracking_dims", "pd_dims"):
            if getattr(self, name) is not None:
                setattr(self, name, tuple(int(d) for d in getattr(self, name)))
                if not getattr(self, name):
                    raise ValueError(f"{name} must name at least one SM dimension (or be None)")
        if self.n_action_steps < 1:
            raise ValueError(f"n_action_steps must be >= 1, got {self.n_action_steps}")
