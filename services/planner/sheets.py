"""Contact sheets of visual action plans: pick and release marked like the paper's figures 5
(circles on the cells of a move) and 6 (an arrow from the pick to the release of a fold)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from shared.plans import VisualActionPlan
from shared.tasks.base import Task

PICK = (40, 90, 255)  # blue, as in the paper
RELEASE = (20, 200, 60)  # green

Point = tuple[float, float]
ActionPixels = Callable[[Any], tuple[Point, Point]]  # action -> (pick, release), image (x, y)


def spec_action_pixels(task: Task, image_size: int) -> ActionPixels | None:
    """Pick and release pixels of a task whose spec declares `pick.row`, `pick.col`,
    `release.row`, `release.col` as pixel fields (a task defined by its data); None otherwise."""
    action = task.spec.action
    wanted = [f"{part}.{axis}" for part in ("pick", "release") for axis in ("row", "col")]
    if any(action.pixels.get(name) != name.split(".")[1] for name in wanted):
        return None
    scale = image_size / float(action.frame or image_size)

    def pixels(a: Any) -> tuple[Point, Point]:
        u = task.action_to_array(a).reshape(-1)
        low = [int(action.encodings.get(n, {}).get("low", 0)) for n in wanted]
        pr, pc, rr, rc = (
            int(u[action.names.index(n)]) + o for n, o in zip(wanted, low, strict=True)
        )
        return ((pc + 0.5) * scale, (pr + 0.5) * scale), ((rc + 0.5) * scale, (rr + 0.5) * scale)

    return pixels


def plan_sheet(
    plan: VisualActionPlan,
    action_pixels: ActionPixels | None,
    arrows: bool = False,
    scale: int = 3,
    text: Callable[[Any], str] = str,
) -> np.ndarray:
    """Images in a row, start to goal; each image before an action shows where it picks and
    releases (circles, or an arrow from pick to release); the action is written underneath
    (`text`: a task's `action_label`)."""
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
            (px, py), (rx, ry) = action_pixels(a) if action_pixels else ((-99, -99), (-99, -99))
            pick = (x0 + px * scale, py * scale)
            release = (x0 + rx * scale, ry * scale)
            r = 4 * scale
            if action_pixels is None:
                pass  # nothing in the image to mark
            elif arrows:
                _arrow(draw, pick, release, width=max(2, scale))
                draw.ellipse(
                    [pick[0] - r, pick[1] - r, pick[0] + r, pick[1] + r], outline=PICK, width=3
                )
            else:
                for (cx, cy), colour in ((pick, PICK), (release, RELEASE)):
                    draw.ellipse([cx - r, cy - r, cx + r, cy + r], outline=colour, width=3)
            draw.text(
                (x0 + 3, tile_h + 15),
                f"{text(a)} p={plan.confidences[i]:.2f}",
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
