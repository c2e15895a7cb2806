"""What the networks make of image observations: the convolutional encoder (DrQ-v2's, or
RLPixTuner's dual-path one), each network's projection of its output, and the two steps a
learner's batch takes on the training device (the gather of distinct frames into stacks, DrQ's
random shift).

An observation with image fields (`uint8[C, H, W]`, stacked k deep: `[k*C, H, W]`, the oldest
frame first) is embedded once per batch by the encoder, which actor and critics share: each image
field, its input scaled to x / 255 - 0.5 on the device that trains, through convolutions of
`channels` of the encoder's kind (`DrQConvolutions`, `DualPath`); float32 fields, flattened,
follow as they are. Each network then has its own `Projection` of the convolutional part to
`features` values (Linear, LayerNorm, tanh), beside the float32 part.

A float32 vector alone (the field `state`) has no encoder: the networks see it through
`l2r.policy.ObservationFilter`, as before image observations existed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import nn

from l2r.protocol.observations import DTYPES, ObservationSpec

CHANNELS, FEATURES = 32, 50
"""DrQ-v2's sizes: 32 channels in every convolution, 50 features out of each projection."""
CONVOLUTIONS = 4
DRQ, DUAL = "drq", "dual"
"""The encoder kinds of a policy spec's "encoder" entry; a spec without one is DrQ-v2's."""
GLOBAL_SIDE, LOCAL_GRID = 32, 8
"""The dual path's sizes: the side its global path averages an image down to, and the grid of cells
its local path keeps."""
MIN_IMAGE_SIDES = {DRQ: 15, DUAL: GLOBAL_SIDE}
"""The smallest height and width each kind takes. DrQ-v2's: (15 - 3) // 2 + 1 = 7, less 2 per later
layer = 1. The dual path's: its global path would otherwise enlarge the image it summarises."""


def image_fields(observation: ObservationSpec) -> list[str]:
    """The fields an encoder convolves: the uint8 ones (checked by `check_observation`)."""
    return [name for name, field in observation.fields.items() if field.dtype == DTYPES["uint8"]]


def check_observation(observation: ObservationSpec, kind: str = DRQ) -> None:
    """ValueError unless the networks can take this observation: the float32 vector `state`
    alone, or image fields uint8[C, H, W] of at least the encoder kind's `MIN_IMAGE_SIDES`,
    optionally beside float32 fields."""
    if observation.vector_width is not None:
        return
    images = image_fields(observation)
    if not images:
        raise ValueError(f"observation {observation}: the networks take the float32 vector 'state', or image "
                         "fields uint8[C, H, W] beside any float32 fields")
    side = MIN_IMAGE_SIDES[kind]
    for name in images:
        shape = observation.fields[name].shape
        if len(shape) != 3 or min(shape[1:]) < side:
            raise ValueError(f"observation field {name!r}: the {kind} encoder takes uint8[C, H, W] images of at least "
                             f"{side} x {side}, got {observation.fields[name]}")


def _conv_side(side: int) -> int:
    side = (side - 3) // 2 + 1
    return side - 2 * (CONVOLUTIONS - 1)


class DrQConvolutions(nn.Sequential):
    """DrQ-v2's view of one image field (B, in_channels, height, width): four 3x3 convolutions of
    `channels` (the first of stride 2, each followed by ReLU), flattened to `out_dim` values."""

    def __init__(self, in_channels: int, height: int, width: int, channels: int):
        layers: list[nn.Module] = []
        for i in range(CONVOLUTIONS):
            layers += [nn.Conv2d(in_channels if i == 0 else channels, channels, 3, stride=2 if i == 0 else 1),
                       nn.ReLU(inplace=True)]
        super().__init__(*layers, nn.Flatten())
        self.out_dim = channels * _conv_side(height) * _conv_side(width)


class DualPath(nn.Module):
    """RLPixTuner's view of one image field (B, in_channels, height, width): two paths of 3x3
    convolutions of `channels`, each followed by ReLU, side by side in `out_dim` values.

    global: the image averaged down to GLOBAL_SIDE x GLOBAL_SIDE, three convolutions of stride 2,
        averaged over what positions remain: `channels` values of the image as a whole (its tone,
        its colour), wherever they come from.
    local: a convolution at full resolution, then two of stride 2, averaged into a LOCAL_GRID x
        LOCAL_GRID grid: `channels` values per cell, kept where in the image they are (detail).
    Padded convolutions: every pixel, the border's too, is seen by each path."""

    def __init__(self, in_channels: int, height: int, width: int, channels: int):
        super().__init__()
        self.global_path = nn.Sequential(nn.AdaptiveAvgPool2d(GLOBAL_SIDE),
                                         *_convolutions(in_channels, channels, [2, 2, 2]),
                                         nn.AdaptiveAvgPool2d(1), nn.Flatten())
        self.local_path = nn.Sequential(*_convolutions(in_channels, channels, [1, 2, 2]),
                                        nn.AdaptiveAvgPool2d(LOCAL_GRID), nn.Flatten())
        self.out_dim = channels * (1 + LOCAL_GRID * LOCAL_GRID)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.global_path(images), self.local_path(images)], dim=-1)


def _convolutions(in_channels: int, channels: int, strides: list[int]) -> list[nn.Module]:
    """Padded 3x3 convolutions of `channels` at these strides, each followed by ReLU."""
    layers: list[nn.Module] = []
    for i, stride in enumerate(strides):
        layers += [nn.Conv2d(in_channels if i == 0 else channels, channels, 3, stride=stride, padding=1),
                   nn.ReLU(inplace=True)]
    return layers


IMAGE_VIEWS = {DRQ: DrQConvolutions, DUAL: DualPath}
"""Each encoder kind's view of one image field."""


class PixelEncoder(nn.Module):
    """Observation fields (a map of tensors, images stacked) -> one embedding per observation:
    each image field's view (`IMAGE_VIEWS` of the encoder's kind), in spec order, then the float32
    fields flattened. `conv_dim` and `vector_dim` are the widths of the two parts."""

    def __init__(self, observation: ObservationSpec, frame_stack: int, channels: int = CHANNELS, kind: str = DRQ):
        super().__init__()
        check_observation(observation, kind)
        self.convs = nn.ModuleDict()
        self.conv_dim = 0
        for name in image_fields(observation):
            c, h, w = observation.fields[name].shape
            self.convs[name] = IMAGE_VIEWS[kind](frame_stack * c, h, w, channels)
            self.conv_dim += self.convs[name].out_dim
        self.vectors = [name for name in observation.fields if name not in self.convs]
        self.vector_dim = frame_stack * sum(math.prod(observation.fields[name].shape) for name in self.vectors)

    def forward(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        parts = [conv(obs[name].float() / 255.0 - 0.5) for name, conv in self.convs.items()]
        parts += [obs[name].flatten(1).float() for name in self.vectors]
        return torch.cat(parts, dim=-1)


class Projection(nn.Module):
    """One network's view of an embedding: the convolutional part through Linear, LayerNorm and
    tanh to `features` values, the float32 part as it is; `out_dim` values in all."""

    def __init__(self, conv_dim: int, vector_dim: int, features: int = FEATURES):
        super().__init__()
        self.split = [conv_dim, vector_dim]
        self.trunk = nn.Sequential(nn.Linear(conv_dim, features), nn.LayerNorm(features), nn.Tanh())
        self.out_dim = features + vector_dim

    def forward(self, embedding: torch.Tensor) -> torch.Tensor:
        pixels, vector = embedding.split(self.split, dim=-1)
        return torch.cat([self.trunk(pixels), vector], dim=-1)


def stack_frames(frames: Mapping[str, torch.Tensor], rows: torch.Tensor) -> dict[str, torch.Tensor]:
    """The stacked observations a sample batch's frames form describes, on the frames' device:
    field f is frames[f][rows], (B, k, *shape), with the k frames concatenated along the first
    field dimension: an image (B, k*C, H, W), oldest frame first; a vector (B, k*width)."""
    return {name: field[rows].flatten(1, 2) for name, field in frames.items()}


def shift_images(images: torch.Tensor, shifts: torch.Tensor, pad: int) -> torch.Tensor:
    """Each image (B, C, H, W) padded by `pad` pixels that repeat its edge, then cropped back to
    H x W at offset shifts[b] = (down, right), each in [0, 2*pad]: an offset of pad is the image
    itself. Any dtype (clamped indices are the replicate padding: no padded copy is made)."""
    _, _, height, width = images.shape
    rows = (shifts[:, :1] - pad + torch.arange(height, device=images.device)).clamp(0, height - 1)
    cols = (shifts[:, 1:] - pad + torch.arange(width, device=images.device)).clamp(0, width - 1)
    batch = torch.arange(len(images), device=images.device)[:, None, None]
    return images[batch, :, rows[:, :, None], cols[:, None, :]].permute(0, 3, 1, 2)


def random_shift(obs: Mapping[str, torch.Tensor], fields: list[str], pad: int) -> dict[str, torch.Tensor]:
    """DrQ's augmentation: each image field of each observation shifted by its own uniformly drawn
    whole-pixel offset in [-pad, pad] (`shift_images`); other fields as they are."""
    shifted = dict(obs)
    for name in fields:
        images = obs[name]
        shifts = torch.randint(0, 2 * pad + 1, (len(images), 2), device=images.device)
        shifted[name] = shift_images(images, shifts, pad)
    return shifted
