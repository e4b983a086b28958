"""Contact sheet of a sequence: colour frames and colour-mapped depth side by side, as one PNG."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from h3edge.io.sequence import Sequence, write_color


def depth_to_rgb(depth: np.ndarray, max_depth: float = 6.0) -> np.ndarray:
    """Turbo colour map of depth (black where invalid)."""
    d = np.clip(depth / max_depth, 0, 1)
    rgb = cv2.cvtColor(cv2.applyColorMap((255 * d).astype(np.uint8), cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    rgb[depth <= 0] = 0
    return rgb


def contact_sheet(seq: Sequence, n: int = 12, cols: int = 4, tile_width: int = 320) -> np.ndarray:
    """``n`` evenly spread frames, each as a colour tile above its depth tile; uint8 RGB."""
    idx = np.linspace(0, len(seq) - 1, min(n, len(seq))).round().astype(int)
    tiles = []
    for i in idx:
        f = seq[int(i)]
        h = int(round(tile_width * f.color.shape[0] / f.color.shape[1]))
        c = cv2.resize(f.color, (tile_width, h), interpolation=cv2.INTER_AREA)
        d = cv2.resize(depth_to_rgb(f.depth), (tile_width, h), interpolation=cv2.INTER_NEAREST)
        cv2.putText(c, f"#{f.index}", (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 0), 1, cv2.LINE_AA)
        tiles.append(np.concatenate([c, d], axis=0))
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[r:r + cols], axis=1) for r in range(0, len(tiles), cols)]
    return np.concatenate(rows, axis=0)


def write_contact_sheet(seq: Sequence, path: str | Path, n: int = 12) -> None:
    write_color(Path(path), contact_sheet(seq, n))
