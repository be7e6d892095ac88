"""Contact sheets of visual action plans: pick and release marked like the paper's figures 5
(circles on the cells of a move) and 6 (an arrow from the pick to the release of a fold)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from shared.plans import VisualActionPlan

PICK = (40, 90, 255)  # blue, as in the paper
RELEASE = (20, 200, 60)  # green

Point = tuple[float, float]
ActionPixels = Callable[[Any], tuple[Point, Point]]  # action -> (pick, release), image (x, y)


def describe(action: Any) -> str:
    text = f"({action.pick.row},{action.pick.col})->({action.release.row},{action.release.col})"
    return text + (f" h{action.height}" if hasattr(action, "height") else "")


def plan_sheet(
    plan: VisualActionPlan, action_pixels: ActionPixels, arrows: bool = False, scale: int = 3
) -> np.ndarray:
    """Images in a row, start to goal; each image before an action shows where it picks and
    releases (circles, or an arrow from pick to release); the action is written underneath."""
    h, w = plan.images[0].shape[:2]
    tile_w, tile_h, caption = w * scale, h * scale, 30
    sheet = Image.new("RGB", (len(plan.images) * (tile_w + 4), tile_h + caption), "white")
    draw = ImageDraw.Draw(sheet)
    for i, image in enumerate(plan.images):
        x0 = i * (tile_w + 4)
        tile = Image.fromarray(image).resize((tile_w, tile_h), Image.Resampling.NEAREST)
        sheet.paste(tile, (x0, 0))
        label = f"node {plan.nodes[i]}" + (" (start)" if i == 0 else "")
        if i < len(plan.actions) and plan.actions[i] is not None:
            a = plan.actions[i]
            (px, py), (rx, ry) = action_pixels(a)
            pick = (x0 + px * scale, py * scale)
            release = (x0 + rx * scale, ry * scale)
            r = 4 * scale
            if arrows:
                _arrow(draw, pick, release, width=max(2, scale))
                draw.ellipse(
                    [pick[0] - r, pick[1] - r, pick[0] + r, pick[1] + r], outline=PICK, width=3
                )
            else:
                for (cx, cy), colour in ((pick, PICK), (release, RELEASE)):
                    draw.ellipse([cx - r, cy - r, cx + r, cy + r], outline=colour, width=3)
            draw.text(
                (x0 + 3, tile_h + 15),
                f"{describe(a)} p={plan.confidences[i]:.2f}",
                fill="black",
            )
        elif i == len(plan.images) - 1:
            label += " (goal)"
        draw.text((x0 + 3, tile_h + 2), label, fill="black")
    return np.asarray(sheet)


def _arrow(draw: ImageDraw.ImageDraw, start: Point, end: Point, width: int) -> None:
    """A green arrow from `start` to `end`, its head at `end`."""
    draw.line([start, end], fill=RELEASE, width=width)
    direction = np.subtract(end, start)
    length = float(np.hypot(*direction))
    if length < 1e-6:
        return
    unit = direction / length
    normal = np.array([-unit[1], unit[0]])
    head = min(4.0 * width, length / 2)
    base = np.asarray(end) - unit * head
    corners = [tuple(end), tuple(base + normal * head / 2), tuple(base - normal * head / 2)]
    draw.polygon(corners, fill=RELEASE)
