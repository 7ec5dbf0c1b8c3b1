"""A small range-image encoder–decoder in plain PyTorch (standard layers only).

Input (B, 6, rings, width) with the channels of projection.CHANNELS, raw units; the net normalises them
itself (fixed per-channel mean/std buffers, saved with the weights). Output (B, classes, rings, width)
logits. Convolutions pad the azimuth axis circularly (the image wraps around) and the ring axis with
zeros. Width must be a multiple of 2 × fold and rings a multiple of 4. Set ``circular = False`` for training on azimuth crops, whose ends do not meet.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn
from torch.nn import functional as F


@dataclass(frozen=True)
class ModelSpec:
    """Architecture hyper-parameters; stored in the model card so weights rebuild the same net."""

    in_channels: int = 6
    num_classes: int = 7
    fold: int = 4  # azimuth columns folded into one pixel
    widths: tuple = (32, 48, 64)  # channels at the folded resolution, 1/2 of it, 1/2 rings × 1/2 of it
    context: tuple = (2, 4)  # azimuth dilation of the two residual blocks at the coarsest level (context width)
    # per-channel normalisation of the raw input (range, x, y, z, intensity, valid)
    mean: tuple = (8.0, 0.0, 0.0, 0.0, 80.0, 0.5)
    std: tuple = (8.0, 8.0, 8.0, 1.5, 50.0, 0.5)

    def as_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "ModelSpec":
        known = set(cls.__dataclass_fields__)
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown model spec key(s): {', '.join(sorted(unknown))}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


class CircConv(nn.Module):
    """Conv2d + BatchNorm + ReLU; azimuth (last axis) padded circularly when ``circular`` else with zeros."""

    def __init__(self, cin: int, cout: int, stride=(1, 1), dilation=(1, 1), act: bool = True):
        super().__init__()
        self.pad_h, self.pad_w = dilation[0], dilation[1]
        self.conv = nn.Conv2d(cin, cout, 3, stride=stride, dilation=dilation, padding=(self.pad_h, 0), bias=False)
        self.bn = nn.BatchNorm2d(cout)
        self.act = act
        self.circular = True

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.pad(x, (self.pad_w, self.pad_w, 0, 0), mode="circular" if self.circular else "constant")
        x = self.bn(self.conv(x))
        return F.relu(x, inplace=True) if self.act else x


class ResBlock(nn.Module):
    """Two 3×3 CircConvs with a residual connection."""

    def __init__(self, c: int, dilation=(1, 1)):
        super().__init__()
        self.a = CircConv(c, c, dilation=dilation)
        self.b = CircConv(c, c, dilation=dilation, act=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(x + self.b(self.a(x)), inplace=True)


class Fuse(nn.Module):
    """Upsample to the skip's size (nearest), concatenate, mix with a 1×1 conv + BN + ReLU."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.fuse = nn.Sequential(nn.Conv2d(cin, cout, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        x = F.interpolate(x, size=skip.shape[-2:], mode="nearest")
        return self.fuse(torch.cat([x, skip], 1))


class RangeNet(nn.Module):
    """Range-image segmentation net; see the module docstring.

    The input's azimuth is folded by ``fold`` into channels (pixel unshuffle: 4 neighbouring columns
    become one pixel with 4× the channels), the encoder works at that coarser azimuth, and the head
    predicts ``fold`` labels per coarse pixel, unfolded back to full resolution. This keeps the network
    cheap on one CPU core while every point still gets its own label.
    """

    def __init__(self, spec: ModelSpec = ModelSpec()):
        super().__init__()
        self.spec = spec
        f = spec.fold
        c1, c2, c3 = spec.widths
        self.register_buffer("mean", torch.tensor(spec.mean, dtype=torch.float32).view(1, -1, 1, 1))
        self.register_buffer("std", torch.tensor(spec.std, dtype=torch.float32).view(1, -1, 1, 1))
        cin = spec.in_channels * f
        self.stem = CircConv(cin, c1)
        self.enc2 = nn.Sequential(CircConv(c1, c2, stride=(2, 2)), ResBlock(c2))
        d1, d2 = spec.context
        self.enc3 = nn.Sequential(CircConv(c2, c3, stride=(2, 1)), ResBlock(c3, (1, d1)), ResBlock(c3, (2, d2)))
        self.fuse2 = Fuse(c3 + c2, c2)
        self.fuse1 = Fuse(c2 + c1, c1)
        self.refine = CircConv(c1, c1)
        self.head = nn.Conv2d(c1 + cin, spec.num_classes * f, 1)

    def set_circular(self, circular: bool) -> "RangeNet":
        """Circular azimuth padding (full scans) or zero padding (training crops)."""
        for m in self.modules():
            if isinstance(m, CircConv):
                m.circular = circular
        return self

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.folded_logits(x)  # (b, k, f, h, w / f)
        b, k, f, h, wf = y.shape
        return y.permute(0, 1, 3, 4, 2).reshape(b, k, h, wf * f)  # unfold azimuth

    def folded_logits(self, x: torch.Tensor) -> torch.Tensor:
        """Logits (B, classes, fold, H, W / fold) before the azimuth unfold: column j * fold + i is [..., i, :, j]."""
        b, _, h, w = x.shape
        f, k = self.spec.fold, self.spec.num_classes
        x = (x - self.mean) / self.std
        x = x.view(b, -1, h, w // f, f).permute(0, 1, 4, 2, 3).reshape(b, -1, h, w // f)  # fold azimuth
        s1 = self.stem(x)
        s2 = self.enc2(s1)
        s3 = self.enc3(s2)
        y = self.refine(self.fuse1(self.fuse2(s3, s2), s1))
        y = self.head(torch.cat([y, x], 1))  # (b, k * f, h, w / f)
        return y.view(b, k, f, h, w // f)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


@torch.no_grad()
def _fold(conv: nn.Conv2d, bn: nn.BatchNorm2d) -> nn.Conv2d:
    """A conv with bias equal to conv followed by bn in eval mode."""
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    fused = nn.Conv2d(conv.in_channels, conv.out_channels, conv.kernel_size, conv.stride, conv.padding,
                      conv.dilation, conv.groups, bias=True)
    fused.weight.copy_(conv.weight * scale.view(-1, 1, 1, 1))
    bias = conv.bias if conv.bias is not None else torch.zeros_like(bn.running_mean)
    fused.bias.copy_((bias - bn.running_mean) * scale + bn.bias)
    return fused


def fold_batchnorm(model: RangeNet) -> RangeNet:
    """Fold every BatchNorm into the conv before it (inference only; same outputs up to float rounding)."""
    model.eval()
    for m in model.modules():
        if isinstance(m, CircConv) and isinstance(m.bn, nn.BatchNorm2d):
            m.conv, m.bn = _fold(m.conv, m.bn), nn.Identity()
        elif isinstance(m, Fuse) and isinstance(m.fuse[1], nn.BatchNorm2d):
            m.fuse = nn.Sequential(_fold(m.fuse[0], m.fuse[1]), m.fuse[2])
    return model
