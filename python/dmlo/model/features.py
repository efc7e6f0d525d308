"""The two Siamese feature nets of §III-C-a: a coarse one at stride 4×8 and a full-resolution refine one."""

from __future__ import annotations

from torch import Tensor, nn

from dmlo.model.config import MatcherConfig
from dmlo.model.deform_conv import DeformConv2d


def conv_bn_act(in_channels: int, out_channels: int, stride: tuple[int, int], slope: float) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm2d(out_channels),
        nn.LeakyReLU(slope),
    )


# Widths and strides of the 9 coarse layers; the strides multiply to 4 rows × 8 columns.
_COARSE_WIDTHS = (16, 16, 32, 32, 32, 32, 32, 32)
_COARSE_STRIDES = ((1, 1), (2, 2), (1, 1), (2, 2), (1, 1), (1, 2), (1, 1), (1, 1), (1, 1))


class CoarseEncoder(nn.Module):
    """9 plain 3×3 convolutions: (B, 2, H, W) → (B, C, H/4, W/8).

    BatchNorm and LeakyReLU sit between the convolutions (the paper's wording), so the last convolution's
    output is the feature itself.
    """

    def __init__(self, config: MatcherConfig) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        channels = 2
        for width, stride in zip(_COARSE_WIDTHS, _COARSE_STRIDES[:-1], strict=True):
            layers.append(conv_bn_act(channels, width, stride, config.leaky_slope))
            channels = width
        layers.append(nn.Conv2d(channels, config.coarse_channels, 3, stride=_COARSE_STRIDES[-1], padding=1))
        self.layers = nn.Sequential(*layers)

    def forward(self, scan: Tensor) -> Tensor:
        return self.layers(scan)


class RefineEncoder(nn.Module):
    """Full-resolution features: plain 3×3 convolutions, then deformable ones; (B, 2, H, W) → (B, Cr, H, W)."""

    def __init__(self, config: MatcherConfig) -> None:
        super().__init__()
        width = config.refine_channels
        kinds = ["plain"] * config.refine_plain_layers + ["deformable"] * config.refine_deformable_layers
        layers: list[nn.Module] = []
        channels = 2
        for index, kind in enumerate(kinds):
            last = index == len(kinds) - 1
            if kind == "plain":
                if last:
                    layers.append(nn.Conv2d(channels, width, 3, padding=1))
                else:
                    layers.append(conv_bn_act(channels, width, (1, 1), config.leaky_slope))
            else:
                layers.append(DeformConv2d(channels, width))
                if not last:
                    layers.extend([nn.BatchNorm2d(width), nn.LeakyReLU(config.leaky_slope)])
            channels = width
        self.layers = nn.Sequential(*layers)

    def forward(self, scan: Tensor) -> Tensor:
        return self.layers(scan)
