"""Training frames' images on the training device, and the ray draw there (the torch backend).

On CUDA a training step that draws its rays on the host copies them up every step and does the
draw under the map lock in Python; here each keyframe's images go to the device once, as they are
kept on the host (uint8 RGB, depth quantised to uint16 in the frame's own unit: 5 bytes a pixel),
with a count of the valid pixels before every ``CHUNK``-pixel chunk (0.25 bytes a pixel), and a
step draws its pixels there: uniformly among the valid pixels, with replacement, exactly as
:meth:`~h3edge.mapping.keyframes.StoredFrame.draw` does on the host, in fixed shapes (no
data-dependent size, no host transfer): a rank r among the valid pixels, its chunk by a search of
the counts, its pixel by the chunk's running count. The newest frame, trained on once before it
is a keyframe or dropped, is uploaded for that step (float32 depth, as integration cleaned it).

On a CPU the tensors share the host arrays (``torch.from_numpy``): only the counts are extra.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import torch

from h3edge.geometry.camera import PIXEL_CENTER_OFFSET, Intrinsics

CHUNK = 32  # pixels a valid-pixel count covers: a draw reads one chunk's depths per ray


def _tensor(a: np.ndarray, device: torch.device) -> torch.Tensor:
    """``a`` on ``device`` (shared with ``a`` on a CPU; a stored frame's arrays are read-only, and
    nothing here writes to them)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # torch: "the given NumPy array is not writable"
        return torch.from_numpy(np.ascontiguousarray(a)).to(device)


@dataclasses.dataclass
class DeviceFrame:
    """One frame's images on the device: colour uint8 (N, 3) and depth (N,) as int16 bits of the
    uint16 steps of ``unit`` metres (0 = invalid), or float32 metres where ``unit`` is 0; N = H W
    pixels, row-major; ``prefix`` int64 (N / CHUNK + 1,) the valid pixels before each chunk;
    ``rot`` (3, 3) float32 such that camera ray @ rot is its world direction, ``origin`` (3,)
    float32 the camera centre (world frame); ``edges``: edge-pixel indices (int64) per setting."""

    color: torch.Tensor
    depth: torch.Tensor
    unit: float
    prefix: torch.Tensor
    n_valid: int
    rot: torch.Tensor
    origin: torch.Tensor
    intrinsics: Intrinsics
    own_bytes: int  # bytes on the device not shared with the host arrays
    edges: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def upload(cls, color: np.ndarray, depth: np.ndarray, unit: float, n_valid: int, pose: np.ndarray,
               intrinsics: Intrinsics, device: torch.device) -> DeviceFrame:
        """``color`` uint8 (H, W, 3), ``depth`` uint16 steps of ``unit`` m (H, W) or float32 metres
        (``unit`` 0), ``n_valid`` its pixels with depth, ``pose`` camera-to-world (OpenCV optical)."""
        c = _tensor(color.reshape(-1, 3), device)
        if unit > 0:
            d = _tensor(np.asarray(depth, np.uint16).reshape(-1).view(np.int16), device)
        else:
            d = _tensor(np.asarray(depth, np.float32).reshape(-1), device)
        valid = d != 0 if unit > 0 else d > 0  # int16 bits: steps above 32767 read negative
        pad = (-len(valid)) % CHUNK
        if pad:
            valid = torch.cat([valid, valid.new_zeros(pad)])
        counts = valid.view(-1, CHUNK).sum(1)
        prefix = torch.cat([counts.new_zeros(1), counts.cumsum(0)])
        rot = _tensor(np.asarray(pose, np.float64)[:3, :3].T.astype(np.float32), device)
        origin = _tensor(np.asarray(pose, np.float64)[:3, 3].astype(np.float32), device)
        own = prefix.numel() * 8 + (0 if device.type == "cpu" else c.numel() + d.numel() * d.element_size())
        return cls(c, d, float(unit), prefix, int(n_valid), rot, origin, intrinsics, own)

    def depth_at(self, pix: torch.Tensor) -> torch.Tensor:
        """Depths (float32 metres, 0 = invalid) of flat pixel indices ``pix``."""
        d = self.depth[pix]
        if self.unit > 0:
            return (d.to(torch.int32) & 0xFFFF).to(torch.float32) * self.unit
        return d

    def draw(self, n: int, generator: torch.Generator | None) -> torch.Tensor:
        """``n`` flat indices (int64) of valid pixels, uniformly with replacement; empty where the
        frame has none."""
        dev = self.depth.device
        if self.n_valid == 0 or n <= 0:
            return torch.zeros(0, dtype=torch.int64, device=dev)
        rank = torch.randint(0, self.n_valid, (n,), generator=generator, device=dev)
        chunk = torch.searchsorted(self.prefix, rank, right=True) - 1  # prefix[c] <= rank < prefix[c + 1]
        start = chunk * CHUNK
        cand = (start[:, None] + torch.arange(CHUNK, device=dev)).clamp(max=len(self.depth) - 1)
        near = self.depth[cand]
        running = (near != 0 if self.unit > 0 else near > 0).cumsum(1)  # a padded slot repeats the last pixel
        within = (running > (rank - self.prefix[chunk])[:, None]).to(torch.int8).argmax(1)
        return start + within

    def rays(self, pix: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Origins (n, 3), world directions with camera z = 1 (n, 3), z-depths (n,) and colours
        (n, 3) in [0, 1] of the pixels ``pix`` (float32, on the device)."""
        k = self.intrinsics
        w = k.width
        u = (pix % w).to(torch.float32) + PIXEL_CENTER_OFFSET
        v = torch.div(pix, w, rounding_mode="floor").to(torch.float32) + PIXEL_CENTER_OFFSET
        cam = torch.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, torch.ones_like(u)], 1)
        return (self.origin.expand(len(pix), 3), cam @ self.rot, self.depth_at(pix),
                self.color[pix].to(torch.float32) / 255.0)

    def edge_pixels(self, key: str, host_edges) -> torch.Tensor:
        """The edge pixels kept as ``key`` on the device (one setting a key: the frame's settings do
        not change), uploaded from ``host_edges()`` (a callable computing them on the host) the
        first time."""
        got = self.edges.get(key)
        if got is None:
            got = self.edges[key] = _tensor(np.asarray(host_edges(), np.int64), self.depth.device)
            self.own_bytes += got.numel() * 8
        return got
