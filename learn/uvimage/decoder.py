"""Seed 001's whole-image convolutional decoder (Appendix E.1).

Input features (B, N) (90 for 10 joints x 3 x 3) are a 1 x 1 x N map; a transposed
convolution (kernel 8) with ReLU makes it 8 x 8 x 384; then each block (transposed conv
4 x 4 stride 2, batch norm, ReLU) doubles the resolution and halves the channels:
five blocks to 256 x 256 x 12; a 3 x 3 convolution gives the output channels (6: front
and back (du, dv, dn)). 3,785,322 parameters for N = 90, 6 outputs ("3.79 million").
"""

from __future__ import annotations

import math

import torch
from torch import nn

#: The seed's whole-T-shirt decoder: start 8 x 8 x 384, output 256 x 256.
START_SIZE = 8
START_CHANNELS = 384


class ImageDecoder(nn.Module):
    """Features (B, in_features) -> images (B, out_channels, size, size).

    Args:
        in_features: N (90 for the seed's pose input).
        out_channels: 3 per panel (6 for front/back).
        size: output side [px], START_SIZE x a power of two (256: five blocks).
        start_channels: channels of the 8 x 8 map (384), halved per block.
    """

    def __init__(self, in_features: int, out_channels: int = 6, *, size: int = 256,
                 start_channels: int = START_CHANNELS) -> None:
        super().__init__()
        blocks = math.log2(size / START_SIZE)
        if size < START_SIZE or blocks != int(blocks):
            raise ValueError(f"image size must be {START_SIZE} x a power of two (8, 16, ..., 256), got {size}")
        blocks = int(blocks)
        if start_channels % (2 ** blocks):
            raise ValueError(f"start_channels ({start_channels}) must be divisible by 2^{blocks} to halve {blocks} times")
        self.config = {"in_features": int(in_features), "out_channels": int(out_channels), "size": int(size),
                       "start_channels": int(start_channels)}
        self.stem = nn.Sequential(nn.ConvTranspose2d(in_features, start_channels, START_SIZE), nn.ReLU(inplace=True))
        layers = []
        channels = start_channels
        for _ in range(blocks):
            layers += [nn.ConvTranspose2d(channels, channels // 2, 4, stride=2, padding=1),
                       nn.BatchNorm2d(channels // 2), nn.ReLU(inplace=True)]
            channels //= 2
        self.blocks = nn.Sequential(*layers)
        self.head = nn.Conv2d(channels, out_channels, 3, padding=1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x = self.stem(features[:, :, None, None])  # (B, 384, 8, 8)
        x = self.blocks(x)  # (B, 384 / 2^k, 8 2^k, 8 2^k)
        return self.head(x)  # (B, out_channels, size, size)
