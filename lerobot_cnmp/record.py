"""Record scripted demonstrations of a CNMP sim into a LeRobotDataset (v3).

Generic over the sims of :data:`lerobot_cnmp.sims.SIMS`: the sim's ``EnvConfig`` builds the env, its expert
drives it for ``demo_length`` steps, and each frame stores the observation *before* the action together with
the action, as LeRobot records. Every demo must succeed (``info["is_success"]`` at its last step). Vector
features are stored as float32; image features (``pixels/<name>`` in the EnvConfig, uint8 H x W x C) as
PNG frames (dtype ``image``), or, for the camera option of a wrapped benchmark (``--cameras``), as video
(dtype ``video``, LeRobot's encoder). Ground truth the policy must not see (the EnvConfig's ``ground_truth``:
dataset feature -> env ``info`` key, e.g. γ with cameras on) is stored under its non-``observation`` name.

The dataset is written atomically: into a staging sibling folder ``.<name>.<pid>.<random>.tmp``, finalized,
given a dataset card (:mod:`lerobot_cnmp.record_card`), then renamed to ``root``. Staging folders left by a
killed recording are removed by the next recording of the same ``root`` (:func:`clean_stale_staging`).

CLI::

    lerobot-cnmp-record --sim cnmp_obstacle2d --root datasets/cnmp_obstacle2d --n_episodes 32 --seed 0
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
from lerobot.configs import FeatureType
from tqdm import tqdm

from lerobot_cnmp.record_card import record_command, write_card
from lerobot_cnmp.sims.cameras import camera_options, camera_video_encoder
from lerobot_cnmp.sims.registry import SIMS, SimSpec

IMAGE_WRITER_THREADS = 2  # threads writing the PNG frames of image features


class DemoFailedError(RuntimeError):
    """The scripted expert's demonstration did not succeed."""


def _get_spec(sim: str) -> SimSpec:
    if sim not in SIMS:
        raise ValueError(f"unknown sim {sim!r}; choose one of {sorted(SIMS)}")
    return SIMS[sim]


def _dataset_features(cfg, spec: SimSpec, video: bool = False) -> dict:
    """LeRobotDataset features from the EnvConfig's features/features_map: float32 vectors (named), images
    (``VISUAL`` features of shape (H, W, C): PNG frames, dtype ``image``, or with ``video`` dtype ``video``),
    and the config's ``ground_truth`` vectors (named by the sim's ``feature_names`` of their ``info`` key)."""
    features = {}
    for key, info_key in getattr(cfg, "ground_truth", {}).items():
        names = spec.feature_names.get(info_key)
        if not names:
            raise ValueError(f"ground-truth feature {key!r} (info[{info_key!r}]) needs its entries' names in the "
                             f"sim's feature_names[{info_key!r}]")
        features[key] = {"dtype": "float32", "shape": (len(names),), "names": list(names)}
    for key, feat in cfg.features.items():
        if feat.type is FeatureType.VISUAL:
            if len(feat.shape) != 3 or not key.startswith("pixels/"):
                raise ValueError(
                    f"image feature {key!r} of shape {feat.shape}: the recorder handles 'pixels/<name>' "
                    "features of shape (height, width, channels)"
                )
            features[cfg.features_map[key]] = {
                "dtype": "video" if video else "image",
                "shape": tuple(feat.shape),
                "names": ["height", "width", "channels"],
            }
            continue
        if len(feat.shape) != 1:
            raise ValueError(
                f"feature {key!r} has shape {feat.shape}; the recorder only handles vectors and images"
            )
        names = spec.feature_names.get(key) or [f"{key}_{i}" for i in range(feat.shape[0])]
        if len(names) != feat.shape[0]:
            raise ValueError(f"{len(names)} names given for feature {key!r} of shape {feat.shape}")
        features[cfg.features_map[key]] = {"dtype": "float32", "shape": tuple(feat.shape), "names": list(names)}
    return features


def _task_description(env) -> str:
    """The env's ``task_description``, looked up through its wrappers (a wrapped third-party env may carry
    it on a wrapper rather than on ``env.unwrapped``); "" if none has one."""
    try:
        return str(env.get_wrapper_attr("task_description") or "")
    except AttributeError:
        return ""


def _frame_value(obs: dict, key: str, dtype: str) -> np.ndarray:
    """The value of env-observation feature ``key`` in ``obs``: ``pixels/<name>`` is the uint8 image
    ``obs["pixels"][name]`` (H, W, C), anything else a float32 vector."""
    if dtype in ("image", "video"):
        return np.asarray(obs["pixels"][key.split("/", 1)[1]], dtype=np.uint8)
    return np.asarray(obs[key], dtype=np.float32)


def parse_action_noise(text: str | float | list | None, action_dim: int) -> np.ndarray | None:
    """``--action_noise``: one std for every action dim or one per dim ("0.3" or "0.3,0.3,0.3,0"); None or
    all zeros: no noise."""
    if text is None:
        return None
    if isinstance(text, str):
        try:
            vals = [float(x) for x in text.split(",") if x.strip()]
        except ValueError as e:
            raise ValueError(f"action_noise must be numbers separated by commas, got {text!r}") from e
    else:
        vals = [float(x) for x in np.atleast_1d(text)]
    if len(vals) == 1:
        vals = vals * action_dim
    if len(vals) != action_dim:
        raise ValueError(f"action_noise has {len(vals)} values; the action has {action_dim} dims (give 1 or {action_dim})")
    noise = np.asarray(vals, dtype=np.float64)
    if not np.isfinite(noise).all() or (noise < 0).any():
        raise ValueError(f"action_noise must be finite and >= 0, got {vals}")
    return noise if noise.any() else None


def record_dataset(
    sim: str,
    root: Path | str,
    n_episodes: int | None = None,
    seed: int = 0,
    repo_id: str | None = None,
    overwrite: bool = False,
    conditions: str | None = None,
    progress: bool = True,
    action_noise: str | float | list | None = None,
    max_failed: int = 0,
    demo_length: int | None = None,
    cameras: list[str] | None = None,
    camera_size: int | None = None,
) -> Path:
    """Record ``n_episodes`` scripted demos of ``sim`` into a LeRobotDataset at ``root``; returns ``root``.

    Args:
        sim: a key of :data:`lerobot_cnmp.sims.SIMS`, e.g. ``"cnmp_obstacle2d"``.
        root: the dataset folder; must not exist unless ``overwrite`` (replaced only once the new one is done).
        n_episodes: number of demos (the sim's default when None).
        seed: episode ``i`` is reset with ``seed + i``.
        repo_id: dataset repo id (default ``lerobot-cnmp/<sim>``).
        overwrite: replace an existing ``root``.
        conditions: the sim's conditions choice, passed to its env config through
            ``SimSpec.config_kwargs`` (the sim's recording default when None).
        progress: show a tqdm progress bar.
        action_noise: DART-style execution noise: the env executes the expert's action plus Gaussian noise of
            this std (one value, or one per action dim; clipped to the action space), the dataset records the
            expert's noise-free action. The expert must be a feedback controller (it acts on the state reached),
            so the demos show recoveries from deviations. None: none. Noise draws are seeded by ``seed``.
        max_failed: drop up to this many demos that fail (e.g. under ``action_noise``) and go on with the next
            seed; the card lists the dropped seeds. 0: the first failed demo stops the recording.
        demo_length: frames per demo (the sim's ``SimSpec.demo_length`` when None), e.g. for a MetaWorld task
            whose expert needs more than the default 150 steps (at most the env's own episode limit).
        cameras, camera_size: a wrapped benchmark's cameras to record as video ``observation.images.<name>``
            (:func:`~lerobot_cnmp.sims.cameras.camera_options`); γ is then stored as ``ground_truth.task_params``.

    Raises:
        ValueError: unknown sim, ``n_episodes < 1``.
        FileExistsError: ``root`` exists and ``overwrite`` is False.
        DemoFailedError: a demo did not succeed (nothing is left on disk).
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    spec = _get_spec(sim)
    if demo_length is not None:
        if int(demo_length) != demo_length or demo_length < 2:
            raise ValueError(f"demo_length must be an integer >= 2, got {demo_length}")
        spec = dataclasses.replace(spec, demo_length=int(demo_length))
    n_episodes = spec.default_episodes if n_episodes is None else int(n_episodes)
    if n_episodes < 1:
        raise ValueError(f"n_episodes must be >= 1, got {n_episodes}")
    if max_failed < 0:
        raise ValueError(f"max_failed must be >= 0, got {max_failed}")
    conditions = spec.default_conditions if conditions is None else conditions
    repo_id = repo_id or f"lerobot-cnmp/{sim}"
    root = Path(root).expanduser().absolute()
    if root.exists() and not overwrite:
        raise FileExistsError(f"dataset folder {root} already exists; pass overwrite=True (--overwrite) to replace it")

    camera_kwargs = camera_options(SIMS, sim, cameras, camera_size)
    cfg = spec.env_config_cls(
        **spec.config_kwargs(conditions),
        **camera_kwargs,
        render_mode=None,
        terminate_on_success=False,
        episode_length=spec.demo_length,
    )
    video = bool(getattr(cfg, "cameras", None))  # a wrapped benchmark's cameras: video, as LeRobot records
    features = _dataset_features(cfg, spec, video=video)
    obs_keys = [k for k in cfg.features if cfg.features_map[k] != "action"]
    obs_dtypes = {k: features[cfg.features_map[k]]["dtype"] for k in obs_keys}
    has_images = bool({"image", "video"} & set(obs_dtypes.values()))
    ground_truth = getattr(cfg, "ground_truth", {})  # dataset feature -> env info key (γ with cameras on)

    try:  # the per-episode "Map" bars of `datasets` would drown our own progress bar
        from datasets.utils import logging as ds_logging

        bars_were_on = ds_logging.is_progress_bar_enabled()
        ds_logging.disable_progress_bar()
    except Exception:  # pragma: no cover
        ds_logging, bars_were_on = None, False

    root.parent.mkdir(parents=True, exist_ok=True)
    clean_stale_staging(root)
    tmp_parent = Path(tempfile.mkdtemp(prefix=f".{root.name}.{os.getpid()}.", suffix=".tmp", dir=root.parent))
    env = ds = None
    try:
        env = gym.make(cfg.gym_id, disable_env_checker=True, **cfg.gym_kwargs)
        base = env.unwrapped
        expert = spec.expert_cls(base, demo_length=spec.demo_length)
        noise = parse_action_noise(action_noise, int(np.prod(env.action_space.shape)))
        noise_rng = np.random.default_rng(seed)
        ds = LeRobotDataset.create(
            repo_id=repo_id,
            fps=cfg.fps,
            features=features,
            root=tmp_parent / "dataset",
            use_videos=video, rgb_encoder=camera_video_encoder() if video else None,
            # PNG encoding of image frames in background threads (finalize stops them)
            image_writer_threads=IMAGE_WRITER_THREADS if has_images else 0,
        )
        labels, kinds, seeds, dropped = [], [], [], []
        t_start = time.perf_counter()
        bar = tqdm(total=n_episodes, desc=f"recording {sim}", unit="episode", disable=not progress)
        attempt = 0
        while len(seeds) < n_episodes:
            i = len(seeds)
            obs, info = env.reset(seed=seed + attempt, options=spec.reset_options(attempt, conditions))
            expert.reset()
            task_str = _task_description(env) or sim
            frames, failure = [], None
            for k in range(spec.demo_length):
                action = np.asarray(expert.act(k), dtype=np.float32)
                frame = {cfg.features_map[key]: _frame_value(obs, key, obs_dtypes[key]) for key in obs_keys}
                frame.update({key: np.asarray(info[i], dtype=np.float32) for key, i in ground_truth.items()})
                frame["action"] = action
                frame["task"] = task_str
                frames.append(frame)
                executed = action
                if noise is not None:
                    executed = np.clip(action + noise_rng.normal(0.0, noise).astype(np.float32),
                                       env.action_space.low, env.action_space.high).astype(np.float32)
                obs, _, terminated, truncated, info = env.step(executed)
                if (terminated or truncated) and k < spec.demo_length - 1:
                    failure = (f"episode {i} (seed {seed + attempt}) of {sim} ended after {k + 1} of "
                               f"{spec.demo_length} steps")
                    break
            if failure is None and not info.get("is_success", False):
                details = {key: val for key, val in info.items() if key != "is_success"}
                failure = f"the expert's demo failed in episode {i} (seed {seed + attempt}) of {sim}: {details}"
            if failure is not None:
                if len(dropped) >= max_failed:
                    raise DemoFailedError(failure if not max_failed else
                                          f"{failure}; {len(dropped)} failed demos were dropped already (max_failed)")
                dropped.append(seed + attempt)
                attempt += 1
                continue
            for frame in frames:
                ds.add_frame(frame)
            ds.save_episode()
            labels.append(spec.episode_label(base))
            kinds.append(str(getattr(base, "condition_kind", conditions)))
            seeds.append(seed + attempt)
            attempt += 1
            bar.update(1)
        bar.close()
        ds.finalize()
        elapsed_s = time.perf_counter() - t_start
        _remove_empty_dirs(tmp_parent / "dataset" / "images")  # LeRobot's PNG staging, emptied per episode
        write_card(
            tmp_parent / "dataset" / "README.md",
            sim=sim,
            spec=spec,
            cfg=cfg,
            features=features,
            repo_id=repo_id,
            n_episodes=n_episodes,
            seed=seed,
            conditions=conditions,
            labels=labels,
            kinds=kinds,
            command=record_command(sim, _display_path(root), n_episodes, seed, repo_id, conditions,
                             None if noise is None else ",".join(f"{v:g}" for v in noise), max_failed,
                             spec.demo_length, camera_kwargs.get("cameras"), camera_kwargs.get("camera_size")),
            elapsed_s=elapsed_s,
            action_noise=noise,
            seeds=seeds,
            dropped=dropped,
        )
        # swap in atomically: the old dataset (if any) is only removed once the new one is complete
        trash = None
        if root.exists():
            trash = tmp_parent / "old"
            root.rename(trash)
        (tmp_parent / "dataset").rename(root)
    except BaseException:
        if ds is not None:  # close the writer before its folder goes away
            try:
                ds.finalize()
            except Exception:
                pass
        raise
    finally:
        if env is not None:
            env.close()
        shutil.rmtree(tmp_parent, ignore_errors=True)
        if ds_logging is not None and bars_were_on:
            ds_logging.enable_progress_bar()
    return root


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def clean_stale_staging(root: Path) -> tuple[list[Path], list[Path]]:
    """Remove the staging folders that killed recordings left beside ``root``; returns ``(removed, unknown)``.

    A recording stages its dataset in ``.<root name>.<pid>.<random>.tmp`` next to ``root`` and removes it when
    it ends; a process killed outright (SIGKILL) cannot, so the next recording of ``root`` removes every such
    folder whose recording process is gone and says so in one line. A folder of that name without a pid
    (staged by an older version) is left alone and named in the line, to be removed by hand.
    """
    prefix = f".{root.name}."
    removed, unknown = [], []
    for folder in sorted(root.parent.glob(glob.escape(prefix) + "*.tmp")):
        owner = folder.name[len(prefix):].split(".", 1)[0]
        if not folder.is_dir():
            continue
        if not owner.isdigit():
            unknown.append(folder)
        elif not _pid_alive(int(owner)):
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
    if removed:
        print(f"removed {len(removed)} staging folder(s) of killed recordings of {root}: "
              f"{[f.name for f in removed]}", file=sys.stderr)
    if unknown:
        print(f"staging folder(s) of an older recorder beside {root}, remove them by hand if no recording runs: "
              f"{[f.name for f in unknown]}", file=sys.stderr)
    return removed, unknown


def _remove_empty_dirs(folder: Path) -> None:
    """Remove ``folder`` and the folders below it that hold no file."""
    if not folder.is_dir():
        return
    for sub in sorted((p for p in folder.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
        if not any(sub.iterdir()):
            sub.rmdir()
    if not any(folder.iterdir()):
        folder.rmdir()


def _display_path(root: Path) -> Path:
    try:
        return root.relative_to(Path.cwd())
    except ValueError:
        return root


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="lerobot-cnmp-record",
        description="Record scripted demonstrations of a CNMP sim into a LeRobotDataset (v3).",
    )
    parser.add_argument("--sim", required=True, help=f"sim to record, one of {sorted(SIMS)}")
    parser.add_argument("--root", required=True, type=Path, help="dataset folder to create")
    parser.add_argument("--n_episodes", type=int, default=None, help="number of demos (sim default if omitted)")
    parser.add_argument("--seed", type=int, default=0, help="episode i is reset with seed + i")
    parser.add_argument("--repo_id", default=None, help="dataset repo id (default lerobot-cnmp/<sim>)")
    parser.add_argument("--conditions", default=None, help="the env's conditions option (sim default if omitted)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")
    parser.add_argument("--action_noise", default=None,
                        help="DART execution noise: std of Gaussian noise added to the executed action, one value or "
                             "one per action dim ('0.3' or '0.3,0.3,0.3,0'); the recorded action stays the expert's")
    parser.add_argument("--demo_length", type=int, default=None,
                        help="frames per demo (default: the sim's; e.g. 300 for a MetaWorld task whose expert needs more "
                             "than 150 steps)")
    parser.add_argument("--max_failed", type=int, default=0,
                        help="drop up to this many failed demos (e.g. under --action_noise) and record the next seed "
                             "instead; the card lists them (default 0: a failed demo stops the recording)")
    parser.add_argument("--cameras", nargs="+", default=None, help="record these cameras as video "
                        "observation.images.<name>; gamma then leaves the observation (kept as ground_truth.task_params)")
    parser.add_argument("--camera_size", type=int, default=None, help="side of the camera images, pixels (default 128)")
    parser.add_argument("--push_to_hub", action="store_true",
                        help="then push the dataset to the Hub as --repo_id (LeRobotDataset.push_to_hub, with its card)")
    parser.add_argument("--private", action="store_true", help="with --push_to_hub: a private repository")
    args = parser.parse_args(argv)
    if args.push_to_hub:
        from lerobot_cnmp.hub import require_online

        if args.repo_id is None:
            parser.error("--push_to_hub needs --repo_id (e.g. you/my_cnmp_dataset)")
        try:  # fail before recording, not after
            require_online(f"dataset {args.root}")
        except RuntimeError as e:
            print(f"error: {e}", file=sys.stderr)
            return 1
    if args.sim not in SIMS:
        parser.error(f"unknown sim {args.sim!r}; choose one of {sorted(SIMS)}")
    if args.n_episodes is not None and args.n_episodes < 1:
        parser.error(f"--n_episodes must be >= 1, got {args.n_episodes}")
    try:
        root = record_dataset(
            args.sim,
            args.root,
            n_episodes=args.n_episodes,
            seed=args.seed,
            repo_id=args.repo_id,
            overwrite=args.overwrite,
            conditions=args.conditions,
            action_noise=args.action_noise,
            max_failed=args.max_failed,
            demo_length=args.demo_length,
            cameras=args.cameras,
            camera_size=args.camera_size,
        )
    except (FileExistsError, DemoFailedError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"dataset written to {root}")
    if args.push_to_hub:
        from lerobot_cnmp.hub import HubUnavailableError, push_dataset

        try:
            print(f"dataset pushed to {push_dataset(root, args.repo_id, private=args.private)}")
        except HubUnavailableError as e:
            print(f"error: {e} (the local dataset is complete at {root})", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
