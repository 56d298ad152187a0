"""Named building blocks of the ResNet generator (paper appendix "Denoising Pix2Pix").

All blocks map (B, C_in, H, W) float32 tensors to (B, C_out, H', W'); the norm layer is a
callable ``norm_layer(num_features) -> nn.Module`` (see :mod:`pix2pix.norms`).
"""

from __future__ import annotations

import torch
from torch import nn

from .norms import NormFactory

__all__ = ["Stem", "Down", "ResidualBlock", "Up", "Head"]


class Stem(nn.Sequential):
    """7x7 convolution with reflection padding, norm, ReLU: (B, C_in, H, W) -> (B, C_out, H, W).

    Reflection padding (not zeros) so that image borders do not look like dark edges.
    """

    def __init__(self, in_channels: int, out_channels: int, norm_layer: NormFactory):
        super().__init__(
            nn.ReflectionPad2d(3),
            nn.Conv2d(in_channels, out_channels, kernel_size=7, padding=0),
            norm_layer(out_channels),
            nn.ReLU(inplace=True),
        )


class Down(nn.Sequential):
    """3x3 stride-2 convolution, norm, ReLU: (B, C_in, H, W) -> (B, C_out, H/2, W/2)."""

    def __init__(self, in_channels: int, out_channels: int, norm_layer: NormFactory):
        super().__init__(
            nn.Conv2d(in_channels, out_channels, kernel_size=3, stride=2, padding=1),
            norm_layer(out_channels),
            nn.ReLU(inplace=True),
        )


class ResidualBlock(nn.Module):
    """x + [reflect-pad, 3x3 conv, norm, ReLU, reflect-pad, 3x3 conv, norm](x); shape-preserving."""

    def __init__(self, channels: int, norm_layer: NormFactory):
        super().__init__()
        self.body = nn.Sequential(
            nn.ReflectionPad2d(1),
            nn.Conv2d(channels, channels, kernel_size=3, padding=0),
            norm_layer(channels),
            nn.ReLU(inplace=True),
            nn.ReflectionPad2d(1),
            nn.Conv2d(channels, channels, kernel_size=3, padding=0),
            norm_layer(channels),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


class Up(nn.Sequential):
    """Stride-2 up-convolution then a 3x3 convolution: (B, C_in, H, W) -> (B, C_out, 2H, 2W).

    A transposed convolution with stride 2 and kernel 3 covers output pixels unevenly (every
    other pixel receives more kernel taps), the source of checkerboard artefacts (Odena et al.
    2016). The 3x3 convolution that follows (as the DSS paper does, after Karras et al.) mixes
    neighbouring pixels and can learn to even the pattern out; pixel-norm after each keeps the
    magnitudes in check.
    """

    def __init__(self, in_channels: int, out_channels: int, norm_layer: NormFactory):
        super().__init__(
            nn.ConvTranspose2d(
                in_channels, out_channels, kernel_size=3, stride=2, padding=1, output_padding=1
            ),
            norm_layer(out_channels),
            nn.ReLU(inplace=True),
            nn.ReflectionPad2d(1),
            nn.Conv2d(out_channels, out_channels, kernel_size=3, padding=0),
            norm_layer(out_channels),
            nn.ReLU(inplace=True),
        )


class Head(nn.Sequential):
    """7x7 convolution with reflection padding to the output channels, **no tanh**.

    The paper removes pix2pix's final tanh so that pixel values are unbounded (renders under a
    point light are not confined to a fixed range, and the network may need to overshoot).
    """

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__(
            nn.ReflectionPad2d(3),
            nn.Conv2d(in_channels, out_channels, kernel_size=7, padding=0),
        )
