"""How the conv encoder reads a camera image (``--policy.image_encoder.*``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from lerobot_cnmp.policy.config_checks import check, is_count


@dataclass
class ImageEncoderConfig:
    """Settings of the conv encoder of each image feature (``use_images``).

    Args:
        keypoints: End the encoder with a spatial softmax (Levine et al., JMLR 2016): each channel of the last
            conv map gives the expected (x, y) image position of its activation, and the embedding is a linear
            map of these 2 x channels coordinates; the last conv layer is not pooled. False: the paper's
            flattened map through a linear layer. Coordinates suit scenes that vary by *where* things are
            (an object's and a goal's positions) and generalize from few demos.
        shift: Random-shift augmentation in training (DrQ, Kostrikov et al. 2021): each episode's image is
            padded by this many pixels (edge values repeated) and cropped back at a random offset, drawn anew
            at every training step. 0: none. Execution always sees the unshifted image.
        downsample: Average-pool the image by this factor before the first conv (1: none). On a CPU the first
            full-resolution conv costs most of the encoder: 2 makes a 128 x 128 camera cost about a fifth.
        center: Subtract the training demos' mean first frame (per pixel; a statistic of the dataset saved
            with the weights, as the SM's mean is) before the conv: with a fixed camera what remains is what
            differs between episodes (where the object and the goal are), not the scene all demos share.
        final_point_weight: Weight of an auxiliary loss in training: a linear head predicts the episode's
            last SM point (normalized; every demonstration has one: where the movement ends, e.g. the goal)
            from the images' embedding, squared error. 0: none. It asks the encoder for what decides the end of
            the movement, which the decoder can otherwise memorize per episode from any feature that tells the
            few demos apart (the object's position).
        point_phases: The phases in [0, 1] of the SM points the auxiliary head of ``final_point_weight``
            predicts (each episode's SM at frame round(phase * (length - 1))); the squared errors are summed
            over the phases, so each point weighs as the last one alone. (1.0,): the last point only. More
            phases ask the encoder for more of the demo's path from its first image, e.g. where the hand went to
            grasp the object midway, not only where the movement ends.
    """

    keypoints: bool = False
    shift: int = 0
    downsample: int = 1
    center: bool = False
    final_point_weight: float = 0.0
    point_phases: tuple[float, ...] = (1.0,)

    def __post_init__(self):
        check(is_count(self.shift), f"image_encoder.shift must be an integer >= 0 (pixels), got {self.shift}")
        check(is_count(self.downsample, 1), f"image_encoder.downsample must be an integer >= 1, got {self.downsample}")
        check(0.0 <= self.final_point_weight < math.inf,
              f"image_encoder.final_point_weight must be a finite number >= 0, got {self.final_point_weight}")
        message = f"image_encoder.point_phases must be a non-empty list of phases in [0, 1], got {self.point_phases!r}"
        try:
            self.point_phases = tuple(float(p) for p in self.point_phases)
        except (TypeError, ValueError):
            raise ValueError(message) from None
        check(len(self.point_phases) > 0 and all(0.0 <= p <= 1.0 for p in self.point_phases), message)
        self.shift, self.downsample = int(self.shift), int(self.downsample)
