"""Top-down pictures of one treadmill env, drawn with numpy (no window, no extra dependency).

The road runs left → right (x: the back of the treadmill's window to its front), across is y (the +y edge at
the top). Agents are coloured squares, adversaries red squares with a dark border; a white pixel block marks
each car's nose.
"""

from __future__ import annotations

import numpy as np

from convoy.envs.treadmill.config import DX, DY

ROAD = np.array([70, 70, 78], np.uint8)
LANE = np.array([200, 200, 120], np.uint8)
ADVERSARY = np.array([220, 40, 40], np.uint8)
AGENT_COLOURS = np.array(
    [[31, 119, 180], [44, 160, 44], [255, 127, 14], [148, 103, 189], [23, 190, 207], [188, 189, 34], [227, 119, 194]],
    np.uint8,
)


def render_frame(
    x: np.ndarray, y: np.ndarray, heading: np.ndarray, n_agents: int, length: int, width: int, scale: int = 4
) -> np.ndarray:
    """RGB image ``[width*scale, length*scale, 3]`` of one env's cars (arrays of shape [C])."""
    img = np.empty((width * scale, length * scale, 3), np.uint8)
    img[:] = ROAD
    img[:, :: 10 * scale][:, :, :] = (ROAD * 0.8).astype(np.uint8)  # distance marks every 10 cells
    for frac in (0.25, 0.5, 0.75):  # lane paint
        row = int((1 - frac) * width * scale)
        img[row, ::6] = LANE
    half = max(scale, 3 * scale // 2)  # cars drawn bigger than a cell so they are visible
    for car in range(len(x)):
        cx = int(x[car]) * scale + scale // 2
        cy = (width - 1 - int(y[car])) * scale + scale // 2
        colour = AGENT_COLOURS[car % len(AGENT_COLOURS)] if car < n_agents else ADVERSARY
        _box(img, cx, cy, half + (1 if car >= n_agents else 0), np.array([20, 20, 20], np.uint8))
        _box(img, cx, cy, half, colour)
        nose_x = cx + int(DX[heading[car]]) * half
        nose_y = cy - int(DY[heading[car]]) * half
        _box(img, nose_x, nose_y, max(1, scale // 2), np.array([255, 255, 255], np.uint8))
    return img


def _box(img: np.ndarray, cx: int, cy: int, half: int, colour: np.ndarray) -> None:
    """Fill a square, clipped to the picture."""
    h, w = img.shape[:2]
    ys = slice(max(0, cy - half), min(h, cy + half + 1))
    img[ys, max(0, cx - half) : min(w, cx + half + 1)] = colour


def write_gif(frames: list[np.ndarray], path: str, fps: int = 15) -> None:
    """Write RGB frames as an animated GIF (Pillow ships with matplotlib)."""
    from PIL import Image

    if not frames:
        raise ValueError("write_gif: no frames to write")
    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0, optimize=True)
