"""Contact sheets of visual action plans: pick and release marked like the paper's figure 5."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from PIL import Image, ImageDraw

from shared.plans import VisualActionPlan

PICK = (40, 90, 255)  # blue circle, as in the paper
RELEASE = (20, 200, 60)  # green circle

CellPixel = Callable[[int, int], tuple[float, float]]


def plan_sheet(plan: VisualActionPlan, cell_pixel: CellPixel, scale: int = 3) -> np.ndarray:
    """Images in a row, start to goal; each image before a move shows where it picks and
    releases; the action is written underneath."""
    h, w = plan.images[0].shape[:2]
    tile_w, tile_h, caption = w * scale, h * scale, 30
    sheet = Image.new("RGB", (len(plan.images) * (tile_w + 4), tile_h + caption), "white")
    draw = ImageDraw.Draw(sheet)
    for i, image in enumerate(plan.images):
        x0 = i * (tile_w + 4)
        tile = Image.fromarray(image).resize((tile_w, tile_h), Image.Resampling.NEAREST)
        sheet.paste(tile, (x0, 0))
        label = f"node {plan.nodes[i]}" + (" (start)" if i == 0 else "")
        if i < len(plan.actions):
            a = plan.actions[i]
            for cell, colour in ((a.pick, PICK), (a.release, RELEASE)):
                px, py = cell_pixel(cell.row, cell.col)
                cx, cy, r = x0 + px * scale, py * scale, 4 * scale
                draw.ellipse([cx - r, cy - r, cx + r, cy + r], outline=colour, width=3)
            draw.text(
                (x0 + 3, tile_h + 15),
                f"({a.pick.row},{a.pick.col})->({a.release.row},{a.release.col}) "
                f"p={plan.confidences[i]:.2f}",
                fill="black",
            )
        elif i == len(plan.images) - 1:
            label += " (goal)"
        draw.text((x0 + 3, tile_h + 2), label, fill="black")
    return np.asarray(sheet)
