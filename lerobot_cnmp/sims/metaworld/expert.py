"""MetaWorld's own scripted expert of a task (``metaworld.policies``) behind the recorder's expert interface."""

from __future__ import annotations

import numpy as np


def expert_policy_name(task: str) -> str:
    """``pick-place-v3`` -> ``SawyerPickPlaceV3Policy`` (MetaWorld's naming of its experts)."""
    if not task.endswith("-v3"):
        raise ValueError(f"not a MetaWorld v3 task name: {task!r}")
    return "Sawyer" + "".join(part.capitalize() for part in task[: -len("-v3")].split("-")) + "V3Policy"


class MetaWorldExpert:
    """Each step, MetaWorld's expert of ``env.task_name`` acting on the env's current 39-dim observation.

    Args:
        env: the unwrapped :class:`~lerobot_cnmp.sims.metaworld.env.MetaWorldEnv` (after ``reset``).
        demo_length: frames of a demonstration (unused by the expert itself; the recorder stops there).
    """

    default_demo_length = 150

    def __init__(self, env, demo_length: int | None = None):
        import metaworld.policies as policies

        name = expert_policy_name(env.task_name)
        if not hasattr(policies, name):
            raise ValueError(f"MetaWorld ships no expert for {env.task_name!r} (no metaworld.policies.{name})")
        self.env = env
        self.policy = getattr(policies, name)()
        self.demo_length = int(demo_length or self.default_demo_length)

    def reset(self) -> None:
        if getattr(self.env, "raw_obs", None) is None:
            raise RuntimeError("reset the env before the expert")

    def act(self, step: int) -> np.ndarray:
        return np.clip(self.policy.get_action(self.env.raw_obs), -1.0, 1.0).astype(np.float32)
