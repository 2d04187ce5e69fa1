"""The episode-level input of E and Q: the normalized task parameters γ and one conv-encoder embedding per image
feature, joined along the last dim; read at an episode's first step (execution) or its first frame (training)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from lerobot_cnmp.execution.sensing import check_finite


def join(parts: list[Tensor]) -> Tensor | None:
    """The parts side by side along the last dim; None when there are none."""
    if not parts:
        return None
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)


def embed(image_encoders: nn.ModuleDict, key: str, images: Tensor, **kwargs) -> Tensor:
    """The embedding of image feature ``key``'s images [B, C, H, W] by its conv encoder, [B, E] (``kwargs``:
    the encoder's training augmentation)."""
    return image_encoders[key.replace(".", "_")](images, **kwargs)


def check_image(key: str, img: Tensor, expected: tuple[int, ...]) -> None:
    """A clear error when image feature ``key`` is not [B, C, H, W] of the trained ``expected`` (C, H, W):
    another resolution, a grayscale frame, channels last."""
    got = tuple(img.shape[1:])
    if img.ndim != 4 or got != expected:
        kind = (" (a grayscale frame: the CNMP was trained on color)" if got[:1] == (1,) and expected[0] == 3
                else " (channels last? LeRobot's image features are [C, H, W])" if got[-1:] == expected[:1] else "")
        raise ValueError(f"image feature {key!r} is {list(img.shape)}, the CNMP was trained on [B, "
                         f"{', '.join(map(str, expected))}]{kind}: give the camera at the trained resolution")


def observed_task_params(spec, batch: dict[str, Tensor]) -> Tensor | None:
    """γ read from an observation (raw units), [B, G]; None when the SM ``spec`` has no task features."""
    parts = []
    for key, size in spec.task_features:
        if key not in batch:
            raise KeyError(f"this CNMP is conditioned on task parameters: the observation needs {key!r}; it has "
                           f"{sorted(batch)}")
        g = batch[key]
        g = g.reshape(g.shape[0], -1) if g.ndim != 3 else g[:, 0]
        if g.shape[-1] != size:
            raise ValueError(f"task feature {key!r} has {g.shape[-1]} values, the CNMP was trained with {size}")
        check_finite(key, g)
        parts.append(g.float())
    return torch.cat(parts, dim=-1) if parts else None


def observed_episode_inputs(config, normalizer, image_encoders: nn.ModuleDict, batch: dict[str, Tensor]
                            ) -> Tensor | None:
    """The episode-level input read from an observation: normalized γ and each image feature's embedding,
    [B, episode_dim]; None when there is neither."""
    gamma = observed_task_params(config.spec, batch)
    parts = [] if gamma is None else [normalizer.task(gamma)]
    for key in config.image_keys:
        if key not in batch:
            raise KeyError(f"this CNMP is conditioned on the image {key!r}; the observation has {sorted(batch)}")
        img = batch[key]
        img = img[:, 0] if img.ndim == 5 else img
        check_image(key, img, tuple(config.input_features[key].shape))
        check_finite(key, img)
        parts.append(embed(image_encoders, key, img))
    return join(parts)
