"""A small LeRobotDataset v3 laid out like an SO-101 teleoperation recording, for tests.

Unlike the simulators' datasets, it has what a real recording has and a sim often has not:
- episodes of different lengths (40..120 frames at 30 fps);
- ``action`` (7 dims: the leader arm's 6 joint targets plus a gripper force command) differs
  from ``observation.state`` (6 dims: the follower's measured joints) in size, names and meaning;
- the state lags the action (first-order lag of ~3 frames plus sensor noise), so state[t] is
  neither action[t] nor action[t-1];
- a per-episode task parameter in ``observation.environment_state`` (the goal position, m);
- one camera, ``observation.images.front``, stored as an AV1 video (48 x 64 RGB).

Built with LeRobot 0.6.1's own writer (``LeRobotDataset.create`` / ``add_frame`` /
``save_episode`` / ``finalize``), deterministic for a seed, ~2-4 s for 6 episodes.

    from realrobot_data import REPO_ID, make_realrobot_dataset  # pytest puts tests/ on sys.path
    root = make_realrobot_dataset(tmp_path / "so101", n_episodes=6, seed=0, video=True)
    ds = LeRobotDataset(REPO_ID, root=root)
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

REPO_ID = "local/so101_realrobot"
FPS = 30
ROBOT_TYPE = "so101_follower"
TASK = "Pick up the block and put it on the goal mark."
MIN_LEN, MAX_LEN = 40, 120
IMAGE_HW = (48, 64)
CAMERA_KEY = "observation.images.front"

JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
STATE_NAMES = [f"{j}.pos" for j in JOINTS]  # LeRobot's so101_follower observation names
ACTION_NAMES = [f"{j}.target" for j in JOINTS] + ["gripper.force"]  # leader targets + force command
ENV_NAMES = ["goal_x", "goal_y", "goal_z"]

HOME = np.array([0.0, -90.0, 90.0, 60.0, 0.0, 5.0])  # degrees; gripper in 0..100 (closed..open)
LAG_FRAMES = 3.0  # time constant of the follower's first-order lag, in frames
STATE_NOISE_DEG = 0.1
FORCE_MAX = 8.0  # gripper.force command at full grasp (N)
L1, L2, SHOULDER_Z = 0.116, 0.135, 0.05  # upper arm, forearm (m), shoulder height


def features(video: bool = True) -> dict:
    """The feature dict given to ``LeRobotDataset.create`` (without LeRobot's default index features)."""
    feats = {
        "observation.state": {"dtype": "float32", "shape": (6,), "names": list(STATE_NAMES)},
        "action": {"dtype": "float32", "shape": (7,), "names": list(ACTION_NAMES)},
        "observation.environment_state": {"dtype": "float32", "shape": (3,), "names": list(ENV_NAMES)},
    }
    if video:
        feats[CAMERA_KEY] = {
            "dtype": "video",
            "shape": (*IMAGE_HW, 3),
            "names": ["height", "width", "channels"],
        }
    return feats


def _min_jerk(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10 - 15 * s + 6 * s**2)


def _goal_pose(goal: np.ndarray, roll: float) -> np.ndarray:
    """Joint angles (deg) that put the gripper above ``goal`` (x, y, z in m): a planar 2-link IK."""
    x, y, z = goal
    pan = np.degrees(np.arctan2(y, x))
    r, h = np.hypot(x, y), z - SHOULDER_Z
    d2 = np.clip(r**2 + h**2, (L1 - L2) ** 2 + 1e-6, (L1 + L2) ** 2 - 1e-6)
    elbow = np.arccos(np.clip((d2 - L1**2 - L2**2) / (2 * L1 * L2), -1, 1))
    lift = np.degrees(np.arctan2(h, r) + np.arctan2(L2 * np.sin(elbow), L1 + L2 * np.cos(elbow)))
    elbow = np.degrees(elbow)
    wrist = np.clip(elbow - lift, -100.0, 100.0)  # keeps the gripper pointing down
    return np.array([pan, -lift, elbow, wrist, roll, 50.0])


def episode_arrays(rng: np.random.Generator, length: int) -> dict[str, np.ndarray]:
    """One episode: action (T, 7), state (T, 6), environment_state (3,)."""
    goal = np.array([rng.uniform(0.14, 0.24), rng.uniform(-0.12, 0.12), rng.uniform(0.02, 0.10)])
    start = HOME + rng.normal(0, [4.0, 3.0, 3.0, 3.0, 5.0, 1.0])
    target = _goal_pose(goal, roll=rng.uniform(-30, 30))
    t = np.arange(length) / (length - 1)
    # reach over the first 75% of the episode with a small mid-course bump, then close the gripper
    s = _min_jerk(t / 0.75)
    bump = np.sin(np.pi * s)[:, None] * rng.normal(0, 6.0, size=5)[None, :]
    joints = start[:5] + (target[:5] - start[:5]) * s[:, None] + bump
    open_close = _min_jerk(t / 0.3) * 75.0 - _min_jerk((t - 0.7) / 0.25) * 70.0  # open on the way, close at the goal
    gripper = start[5] + open_close
    force = FORCE_MAX * _min_jerk((t - 0.8) / 0.2)
    action = np.column_stack([joints, gripper, force])
    # follower: first-order lag towards the leader's target, plus encoder noise
    alpha = 1.0 - np.exp(-1.0 / LAG_FRAMES)
    state = np.empty((length, 6))
    x = start.copy()
    for i in range(length):
        state[i] = x + rng.normal(0, STATE_NOISE_DEG, size=6)
        x = x + alpha * (action[i, :6] - x)
    state[:, 5] = np.clip(state[:, 5], 0.0, 100.0)
    return {"action": action, "state": state, "goal": goal}


def _render(state: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """A (48, 64, 3) uint8 frame: a static green goal mark and a red blob that follows the arm."""
    h, w = IMAGE_HW
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.full((h, w, 3), 40, dtype=np.float32)
    gx, gy = (goal[1] + 0.15) / 0.30 * w, (0.26 - goal[0]) / 0.14 * h
    img[..., 1] += 160 * np.exp(-((xx - gx) ** 2 + (yy - gy) ** 2) / 8.0)
    bx = w / 2 + state[0] / 90.0 * (w / 2)
    by = h * (0.15 + 0.7 * (state[1] + 90.0) / 90.0)
    radius2 = 6.0 + 4.0 * (state[5] / 100.0)
    img[..., 0] += 200 * np.exp(-((xx - bx) ** 2 + (yy - by) ** 2) / radius2)
    return np.clip(img, 0, 255).astype(np.uint8)


def make_realrobot_dataset(root: Path, n_episodes: int = 6, seed: int = 0, video: bool = True) -> Path:
    """Write the dataset at ``root`` (which must not exist) and return ``root``.

    Load it with ``LeRobotDataset(REPO_ID, root=root)``. With ``video=False`` the camera is left out
    (a low-dimensional dataset, faster to build and read).
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    os.environ.setdefault("SVT_LOG", "1")  # the AV1 encoder's banner: errors only
    root = Path(root)
    rng = np.random.default_rng(seed)
    lengths = rng.integers(MIN_LEN, MAX_LEN + 1, size=n_episodes)
    ds = LeRobotDataset.create(
        repo_id=REPO_ID, fps=FPS, features=features(video), root=root, robot_type=ROBOT_TYPE,
        use_videos=video, streaming_encoding=video,
    )
    for length in lengths:
        ep = episode_arrays(rng, int(length))
        env = ep["goal"].astype(np.float32)
        for i in range(int(length)):
            frame = {
                "observation.state": ep["state"][i].astype(np.float32),
                "action": ep["action"][i].astype(np.float32),
                "observation.environment_state": env,
                "task": TASK,
            }
            if video:
                frame[CAMERA_KEY] = _render(ep["state"][i], ep["goal"])
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()
    return root


if __name__ == "__main__":
    import tempfile
    import time

    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        root = make_realrobot_dataset(Path(tmp) / "so101", n_episodes=6, seed=0, video=True)
        t_build = time.perf_counter() - t0
        ds = LeRobotDataset(REPO_ID, root=root)
        print(f"built in {t_build:.2f} s; {ds.num_episodes} episodes, {ds.num_frames} frames, fps {ds.fps}, "
              f"video backend {ds._video_backend}")
        for k, v in ds.features.items():
            print(f"  {k:32s} {v['dtype']:8s} {tuple(v['shape'])} {v.get('names')}")
        print("episode lengths:", [int(e["length"]) for e in ds.meta.episodes])
        t0 = time.perf_counter()
        item = ds[0]
        t_first = time.perf_counter() - t0
        t0 = time.perf_counter()
        n = 50
        for i in range(1, n + 1):
            ds[(i * 37) % len(ds)]
        t_item = (time.perf_counter() - t0) / n
        img = item[CAMERA_KEY]
        print(f"frame 0 {CAMERA_KEY}: {tuple(img.shape)} {img.dtype} range [{img.min():.3f}, {img.max():.3f}]")
        print(f"__getitem__: first {t_first * 1e3:.1f} ms, then {t_item * 1e3:.1f} ms per item")
