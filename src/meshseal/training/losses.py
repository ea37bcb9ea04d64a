"""The seed's losses (Eq. 2-6) and the metrics reported beside them."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def masked_l1(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Mean |a - b| over valid vertices (B, V, C) (mask (B, V)), per component as in the seed's Eq. 2."""
    error = (a - b).abs().mean(-1)
    if mask is None:
        return error.mean()
    return (error * mask).sum() / mask.sum().clamp_min(1.0)


def message_loss(logits: torch.Tensor, message: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy on the logits (the seed uses L1 on sigmoid outputs; BCE trains faster)."""
    return F.binary_cross_entropy_with_logits(logits, message)


def bit_accuracy(logits: torch.Tensor, message: torch.Tensor) -> torch.Tensor:
    """Per-sample fraction of correct bits (B,); a bit is 1 where the logit is positive (Eq. 1)."""
    return ((logits > 0).float() == message).float().mean(-1)


def psnr(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-sample PSNR in dB for images in [0, 1] (B, C, H, W)."""
    mse = ((a - b) ** 2).flatten(1).mean(-1).clamp_min(1e-12)
    return 10.0 * torch.log10(1.0 / mse)


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-sample SSIM (pytorch-msssim, 11x11 Gaussian window)."""
    from pytorch_msssim import ssim as _ssim

    return _ssim(a, b, data_range=1.0, size_average=False)


def normal_angle_deg(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean angle in degrees between unit normals (B, V, 3)."""
    cosine = (F.normalize(a, dim=-1) * F.normalize(b, dim=-1)).sum(-1).clamp(-1.0, 1.0)
    angle = torch.rad2deg(torch.acos(cosine))
    if mask is None:
        return angle.mean()
    return (angle * mask).sum() / mask.sum().clamp_min(1.0)


__all__ = ["masked_l1", "message_loss", "bit_accuracy", "psnr", "ssim", "normal_angle_deg"]
