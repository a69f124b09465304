"""Per-frame appearance (`model.appearance`): a phone's auto-exposure and white balance change through a video, so
the same surface is recorded brighter or bluer from one frame to the next. Without a way to say so, the field
averages the frames and blurs (or bakes a frame's exposure into the part of the scene only that frame sees).

Each training frame gets a small colour transform of the rendered (composited) pixel colour, applied only to the
training renders (`Trainer.losses`): it acts on a frame's final colours, never on density or on a sample's colour,
so it cannot explain geometry or a view-dependent effect. Every other render (new views, `render`, `view`, the
held-out evaluations) is neutral: the identity, which is the training frames' mean appearance (the codes are used
less their mean, `FrameAppearance.centred`), and a penalty pulls each code towards it (`loss.appearance`). Like
the per-image affine colour transforms of Urban Radiance Fields, not NeRF-W's latent codes fed to the colour MLP,
which can also explain view-dependent colour and need test-time optimisation.

Modes:
- "gain": a per-channel gain (log-parametrised: exp(g), 3 numbers a frame). Exposure and white balance are
  per-channel gains of the linear sensor values, and a power-law gamma keeps a gain a gain
  ((g x)^(1/2.2) = g^(1/2.2) x^(1/2.2)). An added per-channel bias (tried: 6 numbers a frame) trades against the
  gain on the narrow range of colours a frame shows and against the field; on the toy room with known gains it
  recovered them less well (slope 0.3-0.65 instead of 0.8-1.0) and its neutral render scored 1.5 dB lower.
- "affine": a 3x3 matrix (identity + a learned offset) and a bias, 12 numbers a frame (Urban Radiance Fields):
  also a colour-correction matrix that changes with the light (channel mixing), at four times the freedom to
  fit what is not appearance (noise, a field still far from the views).

Held-out frames of a video have no trained code: `interpolate_codes` takes theirs from the nearest training frames
in time (exposure changes smoothly through a video), and `livescene eval` reports PSNR both neutral and so.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from .errors import LiveSceneError

MODES = ("off", "gain", "affine")
CODE_SIZE = {"gain": 3, "affine": 12}


class FrameAppearance(nn.Module):
    """One code per dataset frame (rows in dataset order; rows of frames never trained stay at zero = identity)."""

    def __init__(self, mode: str, n_frames: int):
        super().__init__()
        if mode not in CODE_SIZE:
            raise LiveSceneError(f"model.appearance must be one of {', '.join(MODES)}, not {mode!r}")
        if n_frames < 1:
            raise LiveSceneError(f"model.appearance={mode} needs model.appearance_frames >= 1 (the dataset's frame "
                                 f"count; `config.resolve` sets it from the dataset), got {n_frames}")
        self.mode = mode
        self.codes = nn.Parameter(torch.zeros(n_frames, CODE_SIZE[mode]))  # zero = identity: no RNG drawn
        # the frames whose codes train (`Trainer` sets them to its split); saved with the checkpoint
        self.register_buffer("trained", torch.ones(n_frames, dtype=torch.bool))

    def set_trained(self, frames: list[int]) -> None:
        """Only these frames' codes are fitted (the training split): the others are never drawn."""
        self.trained.zero_()
        self.trained[torch.as_tensor(list(frames), dtype=torch.long, device=self.trained.device)] = True

    def centred(self) -> torch.Tensor:
        """(N, D) the codes less their mean over the trained frames, so the identity (neutral) is exactly the
        trained frames' mean appearance. Without it the shared part of all codes is a direction nothing but the
        small penalty holds (the field takes up any shift of them all): with a learning rate that fits the codes
        in a few hundred steps it drifted, and the neutral render with it (16.9 against 26.0 dB on the toy room)."""
        mean = (self.codes * self.trained[:, None]).sum(0) / self.trained.sum().clamp(min=1)
        return self.codes - mean

    def forward(self, rgb: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        """rgb (R, 3) composited colours of rays from dataset frames `frames` (R,) -> as those frames recorded them."""
        return apply_codes(rgb, self.centred()[frames], self.mode)

    def penalty(self, frames: torch.Tensor) -> torch.Tensor:
        """Mean squared code over the batch's rays: per frame in proportion to how often it is drawn, as the colour
        loss is, so the weight means the same at any frame count. On the raw codes: their mean, which `centred`
        takes out, is pulled to zero too (else it has no gradient, and Adam would step on rounding noise)."""
        return (self.codes[frames] ** 2).sum(-1).mean()


def apply_codes(rgb: torch.Tensor, codes: torch.Tensor, mode: str) -> torch.Tensor:
    """Colours (..., 3) through codes (..., D) (or one code (D,) for all): the transform of `mode`."""
    codes = codes.to(rgb.dtype).expand(*rgb.shape[:-1], codes.shape[-1])
    if mode == "gain":
        return rgb * torch.exp(codes[..., :3])
    if mode == "affine":
        offset = codes[..., :9].unflatten(-1, (3, 3))
        return rgb + (offset @ rgb.unsqueeze(-1)).squeeze(-1) + codes[..., 9:12]
    raise LiveSceneError(f"unknown appearance mode {mode!r}: one of {', '.join(MODES)}")


def interpolate_codes(codes: np.ndarray, times: np.ndarray, trained: list[int]) -> np.ndarray:
    """(N, D) a code for every frame: the trained frames' own, every other frame's linearly interpolated in time
    between the trained frames before and after it (the nearest one's beyond the ends). codes (N, D), times (N,)."""
    codes = np.asarray(codes, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64)
    if not len(trained):
        return np.zeros_like(codes)
    tr = np.asarray(sorted(trained, key=lambda i: (times[i], i)))
    out = np.stack([np.interp(times, times[tr], codes[tr, j]) for j in range(codes.shape[1])], -1)
    out[tr] = codes[tr]
    return out


def apply_to_image(rgb: np.ndarray, code: np.ndarray, mode: str) -> np.ndarray:
    """An image (H, W, 3) in [0, 1] as a frame with `code` records it, clipped to [0, 1] like every render."""
    out = apply_codes(torch.from_numpy(np.asarray(rgb, np.float32)), torch.as_tensor(code, dtype=torch.float32), mode)
    return out.clamp(0, 1).numpy()
