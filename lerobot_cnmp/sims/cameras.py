"""Camera observations of a wrapped third-party MuJoCo env (``cameras=[...]`` of ``cnmp_metaworld`` and
``cnmp_so101``): a fast offscreen renderer over the env's own model, and what a camera option means for the
env's features.

With cameras on, the policy sees proprioception and images only: the object and goal positions (γ) leave the
observation. The env still reports γ in ``info["task_params"]``, and the recorder stores it in the dataset as
:data:`GROUND_TRUTH_TASK_PARAMS`, a name that no policy reads (LeRobot's policies take their inputs from
``observation.*`` features), so reports can relate success to the scene without the policy seeing it.
"""

from __future__ import annotations

from dataclasses import dataclass

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


def cameras_replace_task_params(features: dict, features_map: dict, cameras: list[str], size: int) -> None:
    """With ``cameras`` on, the env's features lose ``environment_state`` (γ: ground truth for reports only) and gain
    the cameras' (``pixels/<cam>`` -> ``observation.images.<cam>``); nothing changes without cameras."""
    if not cameras:
        return
    features.pop("environment_state", None)
    features_map.pop("environment_state", None)
    feats, names = camera_features(cameras, size)
    features.update(feats)
    features_map.update(names)


def ground_truth_features(cameras: list[str]) -> dict[str, str]:
    """Dataset feature -> the env ``info`` key the recorder stores it from: γ when cameras replace it, else none."""
    return {GROUND_TRUTH_TASK_PARAMS: "task_params"} if cameras else {}


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


@dataclass(frozen=True)
class FreeView:
    """A camera the model does not define: MuJoCo's free camera looking at ``lookat`` (m, world frame) from
    ``distance`` (m), ``azimuth`` and ``elevation`` (degrees), as a user would mount one over the workspace."""

    lookat: tuple[float, float, float]
    distance: float
    azimuth: float
    elevation: float

    def mjv_camera(self):
        import mujoco

        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        cam.lookat[:] = self.lookat
        cam.distance, cam.azimuth, cam.elevation = self.distance, self.azimuth, self.elevation
        return cam


@dataclass(frozen=True)
class Marker:
    """A flat disc drawn into a frame only (e.g. a goal that the task checks but the model does not show, as a
    coloured mark taped on a real table): centre ``pos`` (m), ``radius`` (m), ``rgba``."""

    pos: tuple[float, float, float]
    radius: float
    rgba: tuple[float, float, float, float]

    def draw(self, geom) -> None:
        import mujoco
        import numpy as np

        mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_CYLINDER, np.array([self.radius, self.radius, 5e-4]),
                            np.asarray(self.pos, dtype=np.float64), np.eye(3).ravel(),
                            np.asarray(self.rgba, dtype=np.float32))


class FastRenderer:
    """``mujoco.Renderer`` over an env's model with shadows, reflections and the skybox off (with software EGL,
    no GPU, these cost most of a frame: MetaWorld's scene at 128 x 128 renders in ~20-30 ms without them).
    Built on first use; :meth:`close` frees the GL context.

    A camera is a name of the model's cameras or a :class:`FreeView` (a viewpoint the model does not define).
    ``markers`` are drawn into the frame only (``mujoco.mjv_initGeom`` on the scene after ``update_scene``,
    as MuJoCo's viewers draw decorations): they are not in the model and nothing collides with them."""

    def __init__(self, model, size: int):
        self.model, self.size = model, int(size)
        self._renderer = None

    def __call__(self, data, camera, markers: tuple[Marker, ...] = ()):
        import mujoco
        import numpy as np

        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, self.size, self.size)
            for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION,
                         mujoco.mjtRndFlag.mjRND_SKYBOX):
                self._renderer.scene.flags[flag] = 0
        self._renderer.update_scene(data, camera=camera.mjv_camera() if isinstance(camera, FreeView) else camera)
        scene = self._renderer.scene
        for marker in markers:
            if scene.ngeom >= scene.maxgeom:
                raise RuntimeError(f"no room for a marker in the scene ({scene.maxgeom} geoms)")
            marker.draw(scene.geoms[scene.ngeom])
            scene.ngeom += 1
        return np.asarray(self._renderer.render(), dtype=np.uint8).copy()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
