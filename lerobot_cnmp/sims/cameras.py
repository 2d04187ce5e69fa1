"""Camera observations of a wrapped third-party MuJoCo env (``cameras=[...]`` of ``cnmp_metaworld`` and
``cnmp_so101``): a fast offscreen renderer over the env's own model, and what a camera option means for the
env's features.

With cameras on, the policy sees proprioception and images only: the object and goal positions (γ) leave the
observation. The env still reports γ in ``info["task_params"]``, and the recorder stores it in the dataset as
:data:`GROUND_TRUTH_TASK_PARAMS`, a name that no policy reads (LeRobot's policies take their inputs from
``observation.*`` features), so reports can relate success to the scene without the policy seeing it.
"""

from __future__ import annotations

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.utils.constants import OBS_IMAGES

GROUND_TRUTH_TASK_PARAMS = "ground_truth.task_params"
"""The dataset feature holding γ when the policy must not see it (cameras on): not an ``observation.*`` key."""

MIN_CAMERA_SIZE = 32


def camera_features(cameras: list[str], size: int) -> tuple[dict[str, PolicyFeature], dict[str, str]]:
    """The env features ``pixels/<cam>`` (uint8 ``size`` x ``size`` x 3) and their policy keys
    ``observation.images.<cam>``."""
    feats = {f"pixels/{c}": PolicyFeature(type=FeatureType.VISUAL, shape=(size, size, 3)) for c in cameras}
    return feats, {f"pixels/{c}": f"{OBS_IMAGES}.{c}" for c in cameras}


def check_cameras(cameras, size: int, available: list[str] | None = None) -> list[str]:
    """``cameras`` as a list of distinct names (each in ``available`` when given) and ``size`` in pixels."""
    if isinstance(cameras, str):
        raise ValueError(f"cameras must be a list of camera names, got the string {cameras!r} (use [{cameras}])")
    cameras = [str(c) for c in cameras or []]
    if len(set(cameras)) != len(cameras):
        raise ValueError(f"cameras must be distinct, got {cameras}")
    if available is not None:
        unknown = [c for c in cameras if c not in available]
        if unknown:
            raise ValueError(f"unknown camera(s) {unknown}; this env's model has {available}")
    if cameras and int(size) < MIN_CAMERA_SIZE:
        raise ValueError(f"camera_size must be at least {MIN_CAMERA_SIZE} pixels, got {size}")
    return cameras


def camera_video_encoder():
    """LeRobot's video encoder settings for the recorded cameras: H.264, 4:4:4, CRF 0 (near-lossless; ~5x the
    size of LeRobot's default AV1: 90 MB for 50 MetaWorld demos with two 128 x 128 cameras). LeRobot's default (AV1, 4:2:0 chroma, CRF 30)
    moves single pixels of a 128 x 128 frame by up to half the range and halves the colour resolution: small
    coloured markers (MetaWorld's goal) change, and an encoder trained on the decoded frames sees a different
    image when it runs on the live camera (docs/cameras.md measures it)."""
    from lerobot.configs.video import RGBEncoderConfig

    return RGBEncoderConfig(vcodec="h264", pix_fmt="yuv444p", crf=0)


def has_camera_option(config_cls) -> bool:
    """Whether an EnvConfig class takes ``cameras`` (a wrapped benchmark with the camera option)."""
    import dataclasses

    return "cameras" in {f.name for f in dataclasses.fields(config_cls)}


def camera_options(sims: dict, sim: str, cameras: list[str] | None, camera_size: int | None) -> dict:
    """The EnvConfig keyword arguments of a recording's ``--cameras`` / ``--camera_size`` for ``sim`` (a key of
    ``sims``, name -> ``SimSpec``); a clear error for a sim without the option or a size without cameras."""
    if not cameras:
        if camera_size is not None:
            raise ValueError("camera_size is given without cameras")
        return {}
    if not has_camera_option(sims[sim].env_config_cls):
        with_option = sorted(n for n, s in sims.items() if has_camera_option(s.env_config_cls))
        raise ValueError(f"sim {sim!r} has no camera option; the sims with one: {with_option}")
    return {"cameras": list(cameras), **({} if camera_size is None else {"camera_size": int(camera_size)})}


class FastRenderer:
    """``mujoco.Renderer`` over an env's model with shadows, reflections and the skybox off (with software EGL,
    no GPU, these cost most of a frame: MetaWorld's scene at 128 x 128 renders in ~20-30 ms without them).
    Built on first use; :meth:`close` frees the GL context."""

    def __init__(self, model, size: int):
        self.model, self.size = model, int(size)
        self._renderer = None

    def __call__(self, data, camera: str):
        import mujoco
        import numpy as np

        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, self.size, self.size)
            for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION,
                         mujoco.mjtRndFlag.mjRND_SKYBOX):
                self._renderer.scene.flags[flag] = 0
        self._renderer.update_scene(data, camera=camera)
        return np.asarray(self._renderer.render(), dtype=np.uint8).copy()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
