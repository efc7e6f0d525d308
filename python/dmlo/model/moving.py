"""A small network that tells, cell by cell, how likely a scan's cylinder image shows a moving object.

Real drives come without SemanticKITTI labels, yet the vehicles around the ego car (a lead car in a jam,
cars beside it) can capture the odometry's consensus. This network is trained on the simulator's moving
labels (class 252) and runs on one scan: the geometry of the cell and its neighbourhood (range and height
above the sensor), not the reflectance, which real sensors scale differently. Its receptive field spans a
car at close range, so it can tell a car body in a lane from the road, kerb and buildings around it.

A small U-Net (`MovingObjectNet`): the image is about thirty times wider than high, so most of its strides
are in the columns.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

# Input channels: log range, height, valid. The range enters as log(1 + r) so that near and far cars
# differ by a comparable amount.
RANGE_SCALE = 4.0
HEIGHT_SCALE = 2.0


def moving_input(range_image: Tensor, height_image: Tensor) -> Tensor:
    """The network input `[B, 3, H, W]` from the range (m, 0 = empty) and the height z (m) of each cell."""
    valid = (range_image > 0).to(range_image.dtype)
    log_range = torch.log1p(range_image.clamp(min=0)) / RANGE_SCALE
    if not torch.onnx.is_in_onnx_export():
        # The exported graph's inputs are checked finite before it runs (and tract cannot run ONNX's IsInf).
        height_image = torch.nan_to_num(height_image, nan=0.0, posinf=0.0, neginf=0.0)
    height = height_image.clamp(-20, 20) / HEIGHT_SCALE
    return torch.stack([log_range * valid, height * valid, valid], dim=1)


def _conv(c_in: int, c_out: int, stride: tuple[int, int] = (1, 1)) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm2d(c_out),
        nn.LeakyReLU(0.1, inplace=True),
    )


class MovingObjectNet(nn.Module):
    """`forward(range [B, H, W], height [B, H, W]) → logits [B, H, W]` (sigmoid: the moving probability).
    H must be a multiple of 4 and W of 32.

    It runs on every scan, so it is kept small: the stem halves the rows and quarters the columns at once (a
    car spans tens of columns but few rows), three levels below it halve the columns (the first also the
    rows), and the logits are upsampled bilinearly to the image."""

    STEM_STRIDE = (2, 4)
    STRIDES = ((2, 2), (1, 2), (1, 2))

    def __init__(self, widths: tuple[int, int, int, int] = (8, 16, 32, 48)) -> None:
        super().__init__()
        self.widths = widths
        self.stem = nn.Sequential(_conv(3, widths[0], self.STEM_STRIDE), _conv(widths[0], widths[0]))
        self.down = nn.ModuleList(
            nn.Sequential(_conv(widths[k], widths[k + 1], stride), _conv(widths[k + 1], widths[k + 1]))
            for k, stride in enumerate(self.STRIDES)
        )
        self.up = nn.ModuleList(
            _conv(widths[k + 1] + widths[k], widths[k]) for k in range(len(self.STRIDES))
        )
        self.head = nn.Conv2d(widths[0], 1, 1)

    def forward(self, range_image: Tensor, height_image: Tensor) -> Tensor:
        x = self.stem(moving_input(range_image, height_image))
        skips = [x]
        for block in self.down:
            x = block(x)
            skips.append(x)
        skips.pop()
        for k in reversed(range(len(self.STRIDES))):
            skip = skips[k]
            x = F.interpolate(x, size=skip.shape[-2:], mode="nearest")
            x = self.up[k](torch.cat([x, skip], dim=1))
        logits = F.interpolate(self.head(x), size=range_image.shape[-2:], mode="bilinear", align_corners=False)
        return logits[:, 0]
