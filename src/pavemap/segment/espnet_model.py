"""ESPNet (Mehta et al., ECCV 2018), the encoder-decoder variant, written for pavemap.

The layer names follow the published Cityscapes checkpoint (``espnet_p_2_q_8.pth``, MIT, Sachin
Mehta) so that ``load_state_dict(strict=True)`` takes it as is; the code is pavemap's own. Every
batch norm has eps 1e-3 and every activation is a per-channel PReLU, as in the trained model.

Shapes: input (B, 3, H, W) with H, W multiples of 8; output (B, classes, H, W) logits.
"""

from __future__ import annotations

import torch
from torch import nn

BN_EPS = 1e-3


class ConvBnAct(nn.Module):
    """conv (no bias) → batch norm → PReLU; keys ``conv``, ``bn``, ``act``."""

    def __init__(self, c_in: int, c_out: int, k: int, stride: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, k, stride=stride, padding=(k - 1) // 2, bias=False)
        self.bn = nn.BatchNorm2d(c_out, eps=BN_EPS)
        self.act = nn.PReLU(c_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(self.conv(x)))


class BnAct(nn.Module):
    """batch norm → PReLU; keys ``bn``, ``act``."""

    def __init__(self, c: int):
        super().__init__()
        self.bn = nn.BatchNorm2d(c, eps=BN_EPS)
        self.act = nn.PReLU(c)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(x))


class Conv(nn.Module):
    """A bias-free conv, optionally dilated; key ``conv``."""

    def __init__(self, c_in: int, c_out: int, k: int, stride: int = 1, dilation: int = 1):
        super().__init__()
        pad = (k - 1) // 2 * dilation
        self.conv = nn.Conv2d(c_in, c_out, k, stride=stride, padding=pad, dilation=dilation, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)


class EspBlock(nn.Module):
    """The ESP module: reduce (``c1``), five dilated 3x3 branches (d = 1, 2, 4, 8, 16), hierarchical
    sums of the dilated ones, concatenation (``nOut`` channels), optional residual, then BN + PReLU.

    ``down``: the reduction is a strided 3x3 (the encoder's down-samplers, whose norm is a plain
    ``bn`` + ``act``); else a 1x1 and the norm is a :class:`BnAct` under the key ``bn``.
    """

    def __init__(self, c_in: int, c_out: int, down: bool = False, residual: bool = True):
        super().__init__()
        n = c_out // 5
        n1 = c_out - 4 * n
        self.c1 = Conv(c_in, n, 3, 2) if down else Conv(c_in, n, 1, 1)
        self.d1 = Conv(n, n1, 3, 1, 1)
        self.d2 = Conv(n, n, 3, 1, 2)
        self.d4 = Conv(n, n, 3, 1, 4)
        self.d8 = Conv(n, n, 3, 1, 8)
        self.d16 = Conv(n, n, 3, 1, 16)
        self.down = down
        self.residual = residual and not down
        if down:
            self.bn = nn.BatchNorm2d(c_out, eps=BN_EPS)
            self.act = nn.PReLU(c_out)
        else:
            self.bn = BnAct(c_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        r = self.c1(x)
        a1 = self.d2(r)
        a2 = a1 + self.d4(r)
        a3 = a2 + self.d8(r)
        a4 = a3 + self.d16(r)
        out = torch.cat([self.d1(r), a1, a2, a3, a4], 1)
        if self.residual:
            out = x + out
        return self.act(self.bn(out)) if self.down else self.bn(out)


class EspEncoder(nn.Module):
    """ESPNet-C: three levels (1/2, 1/4, 1/8) with the input image reinforced at each, ``p`` and ``q``
    ESP blocks at levels 2 and 3."""

    def __init__(self, classes: int = 20, p: int = 2, q: int = 8):
        super().__init__()
        self.level1 = ConvBnAct(3, 16, 3, 2)
        self.b1 = BnAct(16 + 3)
        self.level2_0 = EspBlock(16 + 3, 64, down=True)
        self.level2 = nn.ModuleList([EspBlock(64, 64) for _ in range(p)])
        self.b2 = BnAct(128 + 3)
        self.level3_0 = EspBlock(128 + 3, 128, down=True)
        self.level3 = nn.ModuleList([EspBlock(128, 128) for _ in range(q)])
        self.b3 = BnAct(256)
        self.classifier = Conv(256, classes, 1, 1)


def _pool(x: torch.Tensor, times: int) -> torch.Tensor:
    for _ in range(times):
        x = nn.functional.avg_pool2d(x, 3, stride=2, padding=1)
    return x


class EspNet(nn.Module):
    """ESPNet: the encoder plus the light decoder (two 2x up-convolutions with skip connections and a
    last up-convolution to full resolution). ``forward``: (B, 3, H, W) → (B, classes, H, W)."""

    def __init__(self, classes: int = 20, p: int = 2, q: int = 8):
        super().__init__()
        self.encoder = EspEncoder(classes, p, q)
        self.level3_C = Conv(128 + 3, classes, 1, 1)
        self.br = nn.BatchNorm2d(classes, eps=BN_EPS)
        self.conv = ConvBnAct(16 + classes, classes, 3, 1)
        self.up_l3 = nn.Sequential(nn.ConvTranspose2d(classes, classes, 2, stride=2, bias=False))
        self.combine_l2_l3 = nn.Sequential(BnAct(2 * classes), EspBlock(2 * classes, classes, residual=False))
        self.up_l2 = nn.Sequential(nn.ConvTranspose2d(classes, classes, 2, stride=2, bias=False), BnAct(classes))
        self.classifier = nn.ConvTranspose2d(classes, classes, 2, stride=2, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e = self.encoder
        out0 = e.level1(x)  # (B, 16, H/2, W/2)
        out0_cat = e.b1(torch.cat([out0, _pool(x, 1)], 1))  # (B, 19, H/2, W/2)
        out1_0 = e.level2_0(out0_cat)  # (B, 64, H/4, W/4)
        out1 = out1_0
        for layer in e.level2:
            out1 = layer(out1)
        out1_cat = e.b2(torch.cat([out1, out1_0, _pool(x, 2)], 1))  # (B, 131, H/4, W/4)
        out2_0 = e.level3_0(out1_cat)  # (B, 128, H/8, W/8)
        out2 = out2_0
        for layer in e.level3:
            out2 = layer(out2)
        out2_cat = e.b3(torch.cat([out2_0, out2], 1))  # (B, 256, H/8, W/8)
        up3 = self.up_l3(self.br(e.classifier(out2_cat)))  # (B, C, H/4, W/4)
        comb = self.up_l2(self.combine_l2_l3(torch.cat([self.level3_C(out1_cat), up3], 1)))  # (B, C, H/2, W/2)
        return self.classifier(self.conv(torch.cat([comb, out0], 1)))  # (B, C, H, W)
