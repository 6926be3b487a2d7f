"""A small GIF of every swarm over the importance map ``T^k``.

matplotlib draws the frame once (panels, titles, colour bar); each frame then only repaints the
map pixels inside the panels (the same colour map, cells upscaled) and the drones with Pillow,
which is some hundred times faster than redrawing the figure per frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure
from PIL import Image, ImageDraw, ImageFont

from twin.report.figures import (
    IMPORTANCE_CMAP,
    OBSTACLE_COLOUR,
    draw_map,
    drone_colours,
    importance_label,
    panel_layout,
)
from twin.report.load import RunFiles

MAX_FRAMES = 72
TRAIL = 6
MANY_DRONES = 16  # above this, each drone is a dot without its trail (the GIF stays readable)
TITLE_HEIGHT = 22  # pixels reserved at the top for the per-frame title


def frame_steps(horizon: int, max_frames: int = MAX_FRAMES) -> np.ndarray:
    """Steps shown: every ``ceil((T+1)/max_frames)``-th one, always ending at ``T``."""
    stride = max(1, int(np.ceil((horizon + 1) / max_frames)))
    steps = np.arange(0, horizon + 1, stride)
    return steps if steps[-1] == horizon else np.append(steps, horizon)


def _marker(draw: ImageDraw.ImageDraw, kind: int, x: float, y: float, r: float, fill) -> None:
    """Drone ``kind`` % 4: triangle, square, circle, star (the paper's swarm symbols)."""
    kind %= 4
    if kind == 0:
        pts = [(x, y - r), (x - r, y + 0.8 * r), (x + r, y + 0.8 * r)]
        draw.polygon(pts, fill=fill, outline="white")
    elif kind == 1:
        draw.rectangle(
            [x - 0.8 * r, y - 0.8 * r, x + 0.8 * r, y + 0.8 * r], fill=fill, outline="white"
        )
    elif kind == 2:
        draw.ellipse(
            [x - 0.85 * r, y - 0.85 * r, x + 0.85 * r, y + 0.85 * r], fill=fill, outline="white"
        )
    else:
        angles = np.pi / 2 + np.arange(10) * np.pi / 5
        radii = np.where(np.arange(10) % 2 == 0, 1.2 * r, 0.5 * r)
        pts = list(zip(x + radii * np.cos(angles), y - radii * np.sin(angles), strict=True))
        draw.polygon(pts, fill=fill, outline="white")


def write_animation(rf: RunFiles, path: Path, max_frames: int = MAX_FRAMES, fps: int = 8) -> Path:
    """Write the GIF to ``path`` (a few hundred KB for 4 swarms on a 20 x 30 grid)."""
    swarms = rf.swarms
    nx, ny = rf.obstacles.shape
    rows, cols = panel_layout(len(swarms))
    fig = Figure(figsize=(3.0 * cols + 0.9, 2.2 * rows + 0.5), dpi=80, layout="constrained")
    canvas = FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    image = None
    for ax, swarm in zip(axes, swarms, strict=False):
        image = draw_map(ax, rf.importance[0], rf.obstacles, IMPORTANCE_CMAP, rf.importance_vmax)
        ax.set_title(swarm, fontsize=10)
        ax.set_xlabel("")
        ax.set_ylabel("")
    for ax in axes[len(swarms) :]:
        ax.set_visible(False)
    fig.colorbar(image, ax=axes.tolist(), shrink=0.85, label=importance_label(rf))
    fig.suptitle(" ", fontsize=12)  # room for the per-frame title
    canvas.draw()
    background = np.asarray(canvas.buffer_rgba())[..., :3].copy()
    height = background.shape[0]
    boxes = []  # (left, top, width, height) in pixels of each map
    for ax in axes[: len(swarms)]:
        x0, y0, x1, y1 = ax.get_window_extent().extents
        left, top = round(x0), round(height - y1)
        boxes.append((left, top, round(x1) - left, round(y1 - y0)))

    lut = (np.asarray(colormaps[IMPORTANCE_CMAP](np.linspace(0, 1, 256)))[:, :3] * 255).astype(
        np.uint8
    )
    grey = (np.asarray(to_rgb(OBSTACLE_COLOUR)) * 255).astype(np.uint8)
    positions = {s: rf.positions(s) for s in swarms}
    colours = [
        tuple(int(255 * c) for c in to_rgb(col))
        for col in drone_colours(max(p.shape[1] for p in positions.values()))
    ]
    font = ImageFont.load_default(size=14)
    frames = []
    for k in frame_steps(rf.horizon, max_frames):
        scaled = rf.importance[k] / rf.importance_vmax
        cells = lut[np.clip((scaled * 255).round(), 0, 255).astype(np.int64)]
        cells[rf.obstacles] = grey
        frame = background.copy()
        for left, top, w, h in boxes:
            frame[top : top + h, left : left + w] = np.asarray(
                Image.fromarray(cells).resize((w, h), Image.NEAREST)
            )
        img = Image.fromarray(frame)
        draw = ImageDraw.Draw(img)
        for (left, top, w, h), swarm in zip(boxes, swarms, strict=True):
            pos = positions[swarm]
            kk = min(int(k), len(pos) - 1)
            px = left + (pos[max(0, kk - TRAIL) : kk + 1, :, 1] + 0.5) * w / ny
            py = top + (pos[max(0, kk - TRAIL) : kk + 1, :, 0] + 0.5) * h / nx
            many = pos.shape[1] > MANY_DRONES  # hundreds of drones: a dot each, no trail
            r = max(1.5 if many else 3.0, 0.45 * w / ny)
            for d in range(pos.shape[1]):
                if many:
                    x, y = px[-1, d], py[-1, d]
                    draw.rectangle([x - r, y - r, x + r, y + r], fill=colours[d])
                    continue
                if len(px) > 1:
                    draw.line(list(zip(px[:, d], py[:, d], strict=True)), fill=colours[d], width=2)
                _marker(draw, d, px[-1, d], py[-1, d], r, colours[d])
        draw.rectangle([0, 0, img.width, TITLE_HEIGHT], fill="white")
        draw.text(
            (img.width // 2, 4),
            f"step k = {k} / {rf.horizon}"
            + (f" ({rf.clock(int(k))})" if rf.clock(int(k)) else "")
            + "   importance T^k (bright = congested)",
            fill="black",
            font=font,
            anchor="ma",
        )
        frames.append(
            img.quantize(colors=128, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE)
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    frames[0].save(
        path,
        save_all=True,
        append_images=frames[1:],
        duration=int(1000 / fps),
        loop=0,
        optimize=False,
    )
    return path
