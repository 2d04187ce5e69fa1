"""What the cnmp_metaworld sim needs of MetaWorld without importing it at module import: the task names, their
check, the observation sizes and the control rate (``metaworld`` is imported on first use)."""

from __future__ import annotations

GAMMA_DIM = 6  # object xyz, goal xyz
STATE_DIM = 4  # hand xyz, gripper
DEFAULT_TASK = "reach-v3"
CONTROL_FPS = 80  # MetaWorld: frame_skip 5 x 2.5 ms
MAX_PATH_LENGTH = 500  # MetaWorld's episode limit


def import_metaworld():
    try:
        import metaworld
    except ImportError as e:  # pragma: no cover - depends on the install
        raise ImportError(
            "the cnmp_metaworld env needs MetaWorld: pip install 'lerobot_policy_cnmp[metaworld]' "
            "(metaworld==3.0.0, which works with the pinned mujoco<3.17)"
        ) from e
    return metaworld


def v3_task_names() -> list[str]:
    return sorted(import_metaworld().ALL_V3_ENVIRONMENTS)


def check_task(task: str) -> str:
    names = v3_task_names()
    if task not in names:
        raise ValueError(f"unknown MetaWorld task {task!r}; the v3 tasks are {names}")
    return task
