"""ESPNetv2 (Mehta et al., CVPR 2019) for segmentation, written for pavemap.

The layer names follow the published Cityscapes checkpoint (``espnetv2_s_2.0_city_1024x512.pth``,
EdgeNets, MIT, Sachin Mehta) so that ``load_state_dict(strict=True)`` takes it as is. Encoder: the
EESP network at width s = 2.0 (channels 32, 128, 256, 512; 3 and 7 EESP blocks at levels 3 and 4,
input reinforcement); decoder: efficient pyramid pooling blocks with gated skip connections.

Shapes: input (B, 3, H, W) with H, W multiples of 16; output (B, classes, H, W) logits.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F  # noqa: N812
from torch import nn

CHANNELS = (32, 128, 256, 512)  # s = 2.0
_DILATION = {3: 1, 5: 2, 7: 3, 9: 4, 11: 5, 13: 6, 15: 7, 17: 8}


class CBR(nn.Module):
    """conv (no bias) → BN → PReLU (``act=True``); keys ``conv``, ``bn``, ``act``."""

    def __init__(self, c_in: int, c_out: int, k: int, stride: int = 1, groups: int = 1, act: bool = True):
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, k, stride=stride, padding=(k - 1) // 2, bias=False, groups=groups)
        self.bn = nn.BatchNorm2d(c_out)
        self.act = nn.PReLU(c_out) if act else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.bn(self.conv(x))
        return self.act(x) if self.act is not None else x


class BR(nn.Module):
    """BN → PReLU; keys ``bn``, ``act``."""

    def __init__(self, c: int):
        super().__init__()
        self.bn = nn.BatchNorm2d(c)
        self.act = nn.PReLU(c)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(x))


class DwDilated(nn.Module):
    """Depth-wise dilated 3x3; key ``conv``."""

    def __init__(self, c: int, stride: int, d: int):
        super().__init__()
        self.conv = nn.Conv2d(c, c, 3, stride=stride, padding=d, dilation=d, groups=c, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)


class EESP(nn.Module):
    """Extremely efficient spatial pyramid: grouped 1x1 down to ``c_out / k``, ``k`` depth-wise dilated
    branches summed hierarchically, BN-PReLU, grouped 1x1 expansion, residual + PReLU (not when strided)."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1, k: int = 4, r_lim: int = 7):
        super().__init__()
        n = c_out // k
        self.stride = stride
        self.proj_1x1 = CBR(c_in, n, 1, groups=k)
        sizes = sorted(3 + 2 * i if 3 + 2 * i <= r_lim else 3 for i in range(k))
        self.spp_dw = nn.ModuleList([DwDilated(n, stride, _DILATION[s]) for s in sizes])
        self.conv_1x1_exp = CBR(c_out, c_out, 1, groups=k, act=False)
        self.br_after_cat = BR(c_out)
        self.module_act = nn.PReLU(c_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        r = self.proj_1x1(x)
        outs = [self.spp_dw[0](r)]
        for branch in self.spp_dw[1:]:
            outs.append(branch(r) + outs[-1])
        y = self.conv_1x1_exp(self.br_after_cat(torch.cat(outs, 1)))
        if self.stride == 2:  # the down-sampler's "avg" variant: no residual, no activation here
            return y
        if y.shape == x.shape:
            y = y + x
        return self.module_act(y)


class DownSampler(nn.Module):
    """Strided EESP beside a 3x3 average pool (concatenated), plus the input image pooled to the same
    scale (input reinforcement), PReLU. (B, c_in, h, w), image → (B, c_out, h/2, w/2)."""

    def __init__(self, c_in: int, c_out: int, k: int = 4, r_lim: int = 9):
        super().__init__()
        self.eesp = EESP(c_in, c_out - c_in, stride=2, k=k, r_lim=r_lim)
        self.inp_reinf = nn.Sequential(CBR(3, 3, 3), CBR(3, c_out, 1, act=False))
        self.act = nn.PReLU(c_out)

    def forward(self, x: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        pooled = F.avg_pool2d(x, 3, stride=2, padding=1)
        out = torch.cat([pooled, self.eesp(x)], 1)
        while image.shape[2] != pooled.shape[2]:
            image = F.avg_pool2d(image, 3, stride=2, padding=1)
        return self.act(out + self.inp_reinf(image))


class EESPNet(nn.Module):
    """The ESPNetv2 encoder without its classification levels (level 5)."""

    def __init__(self, reps: tuple[int, int] = (3, 7)):
        super().__init__()
        c = CHANNELS
        self.level1 = CBR(3, c[0], 3, 2)
        self.level2_0 = DownSampler(c[0], c[1], r_lim=13)
        self.level3_0 = DownSampler(c[1], c[2], r_lim=11)
        self.level3 = nn.ModuleList([EESP(c[2], c[2], r_lim=9) for _ in range(reps[0])])
        self.level4_0 = DownSampler(c[2], c[3], r_lim=9)
        self.level4 = nn.ModuleList([EESP(c[3], c[3], r_lim=7) for _ in range(reps[1])])


class _Seq(nn.Module):
    """Holds ``nn.Sequential`` members under the attribute name the checkpoint uses (``cbr`` / ``br``)."""

    def __init__(self, name: str, *layers: nn.Module):
        super().__init__()
        self.name = name
        setattr(self, name, nn.Sequential(*layers))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return getattr(self, self.name)(x)


def _cbr(c_in: int, c_out: int, k: int, groups: int = 1) -> _Seq:
    return _Seq("cbr", nn.Conv2d(c_in, c_out, k, padding=(k - 1) // 2, bias=False, groups=groups),
                nn.BatchNorm2d(c_out), nn.PReLU(c_out))


def _br(c: int) -> _Seq:
    return _Seq("br", nn.BatchNorm2d(c), nn.PReLU(c))


def _shuffle(x: torch.Tensor, groups: int) -> torch.Tensor:
    b, c, h, w = x.shape
    return x.view(b, groups, c // groups, h, w).transpose(1, 2).reshape(b, c, h, w)


class PyrPool(nn.Module):
    """Efficient pyramid pooling: project, depth-wise 3x3 at scales 2, 1.5, 1, 0.5, 0.1 of the map,
    BN-PReLU, channel shuffle, grouped 3x3, 1x1 to ``c_out`` (+ BN-PReLU unless ``last``)."""

    SCALES = (2.0, 1.5, 1.0, 0.5, 0.1)

    def __init__(self, c_in: int, c_proj: int, c_out: int, last: bool = False):
        super().__init__()
        s = len(self.SCALES)
        self.projection_layer = _cbr(c_in, c_proj, 1)
        self.stages = nn.ModuleList(
            [nn.Conv2d(c_proj, c_proj, 3, padding=1, bias=False, groups=c_proj) for _ in range(s)])
        self.merge_layer = nn.Sequential(_br(c_proj * s), nn.Identity(), _cbr(c_proj * s, c_proj, 3, groups=c_proj),
                                         nn.Conv2d(c_proj, c_out, 1, bias=last))
        self.br = None if last else _br(c_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.projection_layer(x)
        h, w = x.shape[2:]
        hs = []
        for scale, stage in zip(self.SCALES, self.stages, strict=True):
            size = (max(5, math.ceil(h * scale)), max(5, math.ceil(w * scale)))
            if scale < 1.0:
                y = F.interpolate(stage(F.adaptive_avg_pool2d(x, size)), (h, w), mode="bilinear", align_corners=True)
            elif scale > 1.0:
                y = F.adaptive_avg_pool2d(stage(F.interpolate(x, size, mode="bilinear", align_corners=True)), (h, w))
            else:
                y = stage(x)
            hs.append(y)
        m = self.merge_layer
        y = m[3](m[2](_shuffle(m[0](torch.cat(hs, 1)), len(self.SCALES))))
        return y if self.br is None else self.br(y)


class GatedPW(nn.Module):
    """Efficient point-wise projection of an encoder map: grouped 3x3 CBR gated by a global-context sigmoid."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.wt_layer = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(c_in, c_out, 1, bias=False), nn.Sigmoid())
        self.expansion_layer = _cbr(c_in, c_out, 3, groups=math.gcd(c_in, c_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.expansion_layer(x) * self.wt_layer(x)


def _up(x: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)


class EspNetV2(nn.Module):
    """ESPNetv2 segmentation network. ``forward``: (B, 3, H, W) → (B, classes, H, W) logits."""

    def __init__(self, classes: int = 20, base_dec: int = 16):
        super().__init__()
        c = CHANNELS
        dec = (4 * base_dec, 3 * base_dec, 2 * base_dec, classes)
        proj = min(classes // 2, base_dec)
        self.base_net = EESPNet()
        self.bu_dec_l1 = PyrPool(c[3], proj, dec[0])
        self.bu_dec_l2 = PyrPool(dec[0], proj, dec[1])
        self.bu_dec_l3 = PyrPool(dec[1], proj, dec[2])
        self.bu_dec_l4 = PyrPool(dec[2], proj, dec[3], last=True)
        self.merge_enc_dec_l2 = GatedPW(c[2], dec[0])
        self.merge_enc_dec_l3 = GatedPW(c[1], dec[1])
        self.merge_enc_dec_l4 = GatedPW(c[0], dec[2])
        self.bu_br_l2 = nn.Sequential(nn.BatchNorm2d(dec[0]), nn.PReLU(dec[0]))
        self.bu_br_l3 = nn.Sequential(nn.BatchNorm2d(dec[1]), nn.PReLU(dec[1]))
        self.bu_br_l4 = nn.Sequential(nn.BatchNorm2d(dec[2]), nn.PReLU(dec[2]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b = self.base_net
        l1 = b.level1(x)  # (B, 32, H/2, W/2)
        l2 = b.level2_0(l1, x)  # (B, 128, H/4, W/4)
        l3 = b.level3_0(l2, x)  # (B, 256, H/8, W/8)
        for layer in b.level3:
            l3 = layer(l3)
        l4 = b.level4_0(l3, x)  # (B, 512, H/16, W/16)
        for layer in b.level4:
            l4 = layer(l4)
        y = self.bu_dec_l1(l4)
        y = self.bu_dec_l2(self.bu_br_l2(_up(y) + self.merge_enc_dec_l2(l3)))
        y = self.bu_dec_l3(self.bu_br_l3(_up(y) + self.merge_enc_dec_l3(l2)))
        y = self.bu_dec_l4(self.bu_br_l4(_up(y) + self.merge_enc_dec_l4(l1)))
        return F.interpolate(y, size=x.shape[2:], mode="bilinear", align_corners=True)
