"""Marker sheets on office paper: the table's markers at true size, tiled on A4 or Letter.

A cell's markers span 600-900 mm, more than any office printer's page. The sheet is cut into
a grid of pages that print at 100% scale, the cuts placed between the markers, never through
one: a marker cut in two and taped together is no longer the square the detector reads. Each
page carries crop marks at its tile's corners, its row and column, what joins it on every
side, the table millimetres its tile spans, every marker's id and place, and a 100 mm scale
bar that shows whether the printer scaled the page. Pages come out as one PDF (matplotlib,
already a dependency) or one SVG each; `shared.workcell.markers_svg` stays the one true-size
sheet.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING
from xml.sax.saxutils import escape

from shared.workcell import CELLS, Workcell, marker_cells

if TYPE_CHECKING:
    from matplotlib.axes import Axes


@dataclass(frozen=True)
class Paper:
    name: str
    width: float  # mm, portrait
    height: float


PAPERS = {"a4": Paper("A4", 210.0, 297.0), "letter": Paper("Letter", 215.9, 279.4)}
# Page margins (mm): outside the tile, where printers print reliably (most leave 3-6 mm blank)
# and the page's header, scale bar, crop marks and joins go.
LEFT, TOP, RIGHT, BOTTOM = 12.0, 28.0, 12.0, 14.0
SCALE_BAR_MM = 100.0
ORIGIN_HALF = 6.0  # the origin cross's half-arm, mm


class SheetError(ValueError):
    """A sheet that cannot be tiled on the paper; the message says what to change."""


@dataclass(frozen=True)
class Box:
    """An axis-aligned box on the table, mm: x right, y away from the camera."""

    left: float
    right: float
    bottom: float
    top: float


@dataclass(frozen=True)
class Tile:
    """One page's share of the sheet."""

    number: int  # 1-based, row-major
    row: int  # 1-based; row 1 is the far side of the table (+y)
    col: int  # 1-based; column 1 is the left
    box: Box  # the table mm it spans
    markers: tuple[int, ...]  # ids printed whole on it
    origin: bool  # the table origin's cross is on it


@dataclass(frozen=True)
class Tiling:
    """The sheet as a grid of pages: neighbours share their tiles' edges, so the trimmed
    pages butt together into the whole sheet."""

    paper: Paper
    landscape: bool
    rows: int
    cols: int
    tiles: tuple[Tile, ...]

    @property
    def page(self) -> tuple[float, float]:
        """The page's (width, height), mm, as it prints."""
        p = self.paper
        return (p.height, p.width) if self.landscape else (p.width, p.height)

    def tile_at(self, row: int, col: int) -> Tile:
        return self.tiles[(row - 1) * self.cols + (col - 1)]


def label_lines(marker_id: int, centre: tuple[float, float], side: float) -> tuple[str, str]:
    """The two lines under a marker: its id, and where it goes on the table (so that a page
    can be placed alone, by measuring)."""
    return (
        f"marker {marker_id}",
        f"centre x {centre[0]:.1f}, y {centre[1]:.1f} mm; side {side:.1f} mm",
    )


LABEL_SIZES = (3.0, 2.2)  # mm: the marker's id line and its place line
LABEL_DEPTH = 9.0  # mm below the marker that its two label lines take


def _text_width(text: str, size: float) -> float:
    """A generous estimate of a sans-serif line's width, mm."""
    return 0.6 * size * len(text)


def keep_outs(workcell: Workcell) -> tuple[dict[int, Box], Box | None]:
    """What no cut may cross: each marker with a quiet margin (the detector needs white round
    its black border) and its label below, and the origin's cross with its label
    (None where it would overlap a marker: it is then not drawn)."""
    boxes = {}
    for m in workcell.markers:
        quiet = _quiet(m.side_mm)
        lines = label_lines(m.id, m.centre_mm, m.side_mm)
        wide = max(_text_width(t, size) for t, size in zip(lines, LABEL_SIZES, strict=True))
        half = max(m.side_mm / 2 + quiet, wide / 2 + 1.0)
        (x, y), h = m.centre_mm, m.side_mm / 2
        boxes[m.id] = Box(x - half, x + half, y - h - quiet - LABEL_DEPTH, y + h + quiet)
    origin = Box(-ORIGIN_HALF - 1, ORIGIN_HALF + _text_width("table origin", 2.2) + 2, -7.0, 7.0)
    if any(_overlap(origin, box) for box in boxes.values()):
        return boxes, None
    return boxes, origin


def _quiet(side: float) -> float:
    """The white kept round a marker on its page, mm: one of its cells, within 4..10 mm (the
    page's paper goes on beyond it, so a large marker needs no more to fit a page)."""
    return min(max(side / CELLS, 4.0), 10.0)


def _overlap(a: Box, b: Box) -> bool:
    return a.left < b.right and b.left < a.right and a.bottom < b.top and b.bottom < a.top


def _cuts(low: float, high: float, step: float, keep: Sequence[tuple[float, float]]) -> list[float]:
    """Edges from `low` to `high`, at most `step` apart, none strictly inside a `keep`
    interval: each cut as far on as the page allows, pulled back to the start of an interval
    it would fall in. The fewest pages there can be on this line."""
    merged: list[list[float]] = []
    for a, b in sorted(keep):
        if merged and a < merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    edges = [low]
    while high - edges[-1] > step + 1e-9:
        cut = edges[-1] + step
        for a, b in merged:
            if a < cut < b:
                cut = a
                break
        if cut <= edges[-1] + 1e-9:
            raise SheetError(
                f"{step:.0f} mm of page: a marker with its margin and label is wider than that"
            )
        edges.append(cut)
    edges.append(high)
    return edges


def _balanced(low: float, high: float, step: float, keep: list[tuple[float, float]]) -> list[float]:
    """`_cuts` over the sheet widened to fill its pages evenly, when that takes no more
    pages (full tiles, the spare paper shared by both ends); else over the sheet itself."""
    tight = _cuts(low, high, step, keep)
    pages = len(tight) - 1
    middle, span = (low + high) / 2, pages * step
    if span <= high - low:
        return tight
    try:
        wide = _cuts(middle - span / 2, middle + span / 2, step, keep)
    except SheetError:
        return tight
    return wide if len(wide) - 1 == pages else tight


def tile(workcell: Workcell, paper: Paper) -> Tiling:
    """The sheet cut into pages of `paper`, portrait or landscape, whichever takes fewer
    (portrait on a tie), with every marker whole on one page."""
    boxes, origin = keep_outs(workcell)
    every = [*boxes.values(), *([origin] if origin else [])]
    margin = 5.0
    left = min(b.left for b in every) - margin
    right = max(b.right for b in every) + margin
    bottom = min(b.bottom for b in every) - margin
    top = max(b.top for b in every) + margin
    xs = [(b.left, b.right) for b in every]
    ys = [(-b.top, -b.bottom) for b in every]  # rows run from the top (far side) down
    best, reason = None, ""
    for landscape in (False, True):
        page_w, page_h = (paper.height, paper.width) if landscape else (paper.width, paper.height)
        try:
            cols = _balanced(left, right, page_w - LEFT - RIGHT, xs)
            rows = [-v for v in _balanced(-top, -bottom, page_h - TOP - BOTTOM, ys)]
        except SheetError as exc:
            reason = str(exc)
            continue
        count = (len(cols) - 1) * (len(rows) - 1)
        if best is None or count < best[0]:
            best = (count, landscape, cols, rows)
    if best is None:
        raise SheetError(
            f"the markers do not fit on {paper.name} pages ({reason}): use smaller markers, "
            "or --paper none for one true-size sheet"
        )
    _, landscape, cols, rows = best
    tiles = []
    for r in range(len(rows) - 1):
        for c in range(len(cols) - 1):
            box = Box(cols[c], cols[c + 1], rows[r + 1], rows[r])
            inside = tuple(i for i, b in boxes.items() if _contains(box, b))
            tiles.append(
                Tile(
                    number=len(tiles) + 1,
                    row=r + 1,
                    col=c + 1,
                    box=box,
                    markers=inside,
                    origin=origin is not None and _contains(box, origin),
                )
            )
    tiling = Tiling(paper, landscape, len(rows) - 1, len(cols) - 1, tuple(tiles))
    placed = sorted(i for t in tiling.tiles for i in t.markers)
    assert placed == sorted(boxes), "every marker whole on exactly one page"
    return tiling


def _contains(outer: Box, inner: Box, slack: float = 1e-6) -> bool:
    return (
        outer.left - slack <= inner.left
        and inner.right <= outer.right + slack
        and outer.bottom - slack <= inner.bottom
        and inner.top <= outer.top + slack
    )


# ----- pages: shapes in page millimetres (y down), written as SVG or PDF -----


@dataclass(frozen=True)
class Rect:
    x: float
    y: float
    w: float
    h: float
    fill: str = "black"


@dataclass(frozen=True)
class Line:
    points: tuple[tuple[float, float], ...]
    width: float = 0.2
    colour: str = "black"
    dashed: bool = False
    ident: str | None = None


@dataclass(frozen=True)
class Text:
    x: float
    y: float  # the baseline
    text: str
    size: float = 2.5  # mm
    anchor: str = "start"  # start, middle, end
    rotate: float = 0.0  # degrees, clockwise on the page
    bold: bool = False


@dataclass
class Group:
    ident: str
    items: list[Rect | Line | Text | Group] = field(default_factory=list)


@dataclass
class Page:
    width: float
    height: float
    title: str
    items: list[Rect | Line | Text | Group] = field(default_factory=list)


def _marker_group(
    workcell: Workcell, marker_id: int, at: Callable[[float, float], tuple[float, float]]
) -> Group:
    """A marker's black cells (each row's runs as one rectangle: no hairline seams between
    cells in a viewer) and its label centred below it."""
    marker = next(m for m in workcell.markers if m.id == marker_id)
    grid = marker_cells(marker_id)
    n = grid.shape[0]
    cell = marker.side_mm / n
    half = marker.side_mm / 2
    x0, y0 = at(marker.centre_mm[0] - half, marker.centre_mm[1] + half)
    group = Group(f"marker-{marker_id}")
    for r in range(n):
        c = 0
        while c < n:
            if grid[r, c]:
                c += 1
                continue
            start = c
            while c < n and not grid[r, c]:
                c += 1
            group.items.append(Rect(x0 + start * cell, y0 + r * cell, (c - start) * cell, cell))
    cx = x0 + half
    first, second = label_lines(marker_id, marker.centre_mm, marker.side_mm)
    below = y0 + marker.side_mm + _quiet(marker.side_mm)
    group.items.append(Text(cx, below + 3.0, first, LABEL_SIZES[0], "middle", bold=True))
    group.items.append(Text(cx, below + 6.5, second, LABEL_SIZES[1], "middle"))
    return group


def pages(workcell: Workcell, tiling: Tiling, title: str) -> list[Page]:
    """Every tile as a printable page."""
    width, height = tiling.page
    tile_w, tile_h = width - LEFT - RIGHT, height - TOP - BOTTOM
    out = []
    for t in tiling.tiles:
        box = t.box

        def at(x: float, y: float, box: Box = box) -> tuple[float, float]:
            return LEFT + (x - box.left), TOP + (box.top - y)

        page = Page(width, height, f"{title}: page {t.number} of {len(tiling.tiles)}")
        w, h = box.right - box.left, box.top - box.bottom
        assert w <= tile_w + 1e-6 and h <= tile_h + 1e-6
        x1, y1 = LEFT + w, TOP + h  # the tile's far corner on the page
        page.items.append(
            Text(LEFT, 7.0, f"{title}: page {t.number} of {len(tiling.tiles)}, row {t.row} "
                 f"of {tiling.rows}, column {t.col} of {tiling.cols}", 3.0, bold=True)
        )  # fmt: skip
        page.items.append(
            Text(LEFT, 11.5, f"table x {box.left:.1f} to {box.right:.1f} mm, y {box.bottom:.1f} "
                 f"to {box.top:.1f} mm; this edge of the page faces away from the camera (+y)",
                 2.2)
        )  # fmt: skip
        page.items.extend(_scale_bar())
        # the tile's edges (cut along them) and crop marks beyond its corners
        outline = ((LEFT, TOP), (x1, TOP), (x1, y1), (LEFT, y1), (LEFT, TOP))
        page.items.append(Line(outline, 0.15, "#9a9a9a", dashed=True, ident="tile"))
        for cx, cy, dx, dy in ((LEFT, TOP, -1, -1), (x1, TOP, 1, -1), (x1, y1, 1, 1),
                               (LEFT, y1, -1, 1)):  # fmt: skip
            page.items.append(Line(((cx + dx * 1.5, cy), (cx + dx * 6.5, cy)), 0.2))
            page.items.append(Line(((cx, cy + dy * 1.5), (cx, cy + dy * 6.5)), 0.2))
        page.items.extend(_joins(tiling, t, x1, y1))
        for marker_id in t.markers:
            page.items.append(_marker_group(workcell, marker_id, at))
        if t.origin:
            ox, oy = at(0.0, 0.0)
            arm = ORIGIN_HALF
            cross = Group("origin", [
                Line(((ox - arm, oy), (ox + arm, oy)), 0.3),
                Line(((ox, oy - arm), (ox, oy + arm)), 0.3),
                Text(ox + 2.0, oy - 2.0, "table origin", 2.2),
            ])  # fmt: skip
            page.items.append(cross)
        out.append(page)
    return out


def _scale_bar() -> list[Line | Text]:
    """A 100 mm bar with a tick every 10 mm, to measure after printing."""
    x0, y = LEFT + 8.0, 16.0
    x1 = x0 + SCALE_BAR_MM
    items: list[Line | Text] = [Line(((x0, y), (x1, y)), 0.3, ident="scale-bar")]
    for k in range(11):
        x = x0 + 10.0 * k
        items.append(Line(((x, y - (2.0 if k in (0, 10) else 1.0)), (x, y)), 0.2))
    items.append(Text(x0 - 2.0, y + 0.8, "0", 2.2, "end"))
    items.append(Text(x1 + 2.0, y + 0.8, "100 mm", 2.2))
    items.append(
        Text(LEFT, y + 4.5, "Measure the bar: not 100 mm? Print again at 100% (actual size, "
             "no fit to page).", 2.0)
    )  # fmt: skip
    return items


def _joins(tiling: Tiling, t: Tile, x1: float, y1: float) -> list[Line | Text]:
    """On each edge that another page continues: a tick across the edge's middle and that
    page's number, so that the pages go together in one way only."""
    items: list[Line | Text] = []
    mid_x, mid_y = (LEFT + x1) / 2, (TOP + y1) / 2
    out = 1.5  # ticks start this far outside the tile
    sides = (  # the neighbour's row and column, the tick's start and length, the text, its turn
        (t.row - 1, t.col, (mid_x, TOP - out), (0, -3), (mid_x + 2, TOP - 2), 0.0),
        (t.row + 1, t.col, (mid_x, y1 + out), (0, 4), (mid_x + 2, y1 + 5), 0.0),
        (t.row, t.col - 1, (LEFT - out, mid_y), (-4, 0), (LEFT - 2.5, mid_y - 2), -90.0),
        (t.row, t.col + 1, (x1 + out, mid_y), (4, 0), (x1 + 2.5, mid_y + 2), 90.0),
    )
    for row, col, (x, y), (dx, dy), (tx, ty), rotate in sides:
        if 1 <= row <= tiling.rows and 1 <= col <= tiling.cols:
            other = tiling.tile_at(row, col)
            items.append(Line(((x, y), (x + dx, y + dy)), 0.3))
            text = f"page {other.number} (row {row}, column {col}) joins here"
            items.append(Text(tx, ty, text, 2.0, rotate=rotate))
    return items


# ----- writers -----


def page_svg(page: Page) -> str:
    """One page as SVG, its size in millimetres (one user unit a millimetre)."""
    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{page.width:g}mm" '
        f'height="{page.height:g}mm" viewBox="0 0 {page.width:g} {page.height:g}">',
        f"<title>{escape(page.title)}</title>",
        f'<rect x="0" y="0" width="{page.width:g}" height="{page.height:g}" fill="white"/>',
    ]
    parts.extend(_svg(item) for item in page.items)
    parts.append("</svg>")
    return "\n".join(parts) + "\n"


def _svg(item: Rect | Line | Text | Group) -> str:
    if isinstance(item, Group):
        return f'<g id="{item.ident}">' + "".join(_svg(i) for i in item.items) + "</g>"
    if isinstance(item, Rect):
        return (
            f'<rect x="{item.x:.3f}" y="{item.y:.3f}" width="{item.w:.3f}" height="{item.h:.3f}" '
            f'fill="{item.fill}" shape-rendering="crispEdges"/>'
        )
    if isinstance(item, Line):
        path = " L ".join(f"{x:.3f} {y:.3f}" for x, y in item.points)
        ident = f' id="{item.ident}"' if item.ident else ""
        dash = ' stroke-dasharray="2 1.5"' if item.dashed else ""
        return (
            f'<path{ident} d="M {path}" stroke="{item.colour}" stroke-width="{item.width:g}" '
            f'fill="none"{dash}/>'
        )
    anchor = {"start": "start", "middle": "middle", "end": "end"}[item.anchor]
    turn = f' transform="rotate({item.rotate:g} {item.x:.3f} {item.y:.3f})"' if item.rotate else ""
    weight = ' font-weight="bold"' if item.bold else ""
    return (
        f'<text x="{item.x:.3f}" y="{item.y:.3f}" font-size="{item.size:g}" '
        f'font-family="sans-serif" text-anchor="{anchor}"{weight}{turn}>{escape(item.text)}</text>'
    )


def write_pdf(pages_: Sequence[Page], path: Path) -> None:
    """Every page into one PDF, each at its paper's size: a PDF prints at 100% where SVG in a
    browser is often scaled to fit."""
    from matplotlib.backends.backend_pdf import PdfPages
    from matplotlib.figure import Figure

    metadata = {"Creator": "lsr workcell markers", "CreationDate": None, "Title": None}
    with PdfPages(path, metadata=metadata) as pdf:
        for page in pages_:
            figure = Figure(figsize=(page.width / 25.4, page.height / 25.4))
            axes = figure.add_axes((0, 0, 1, 1))
            axes.set_xlim(0, page.width)
            axes.set_ylim(page.height, 0)  # page millimetres, y down as in SVG
            axes.set_axis_off()
            for item in page.items:
                _draw(axes, item)
            pdf.savefig(figure)


POINTS_PER_MM = 72 / 25.4


def _draw(axes: Axes, item: Rect | Line | Text | Group) -> None:
    from matplotlib.patches import Rectangle

    if isinstance(item, Group):
        for inner in item.items:
            _draw(axes, inner)
    elif isinstance(item, Rect):
        axes.add_patch(Rectangle((item.x, item.y), item.w, item.h, facecolor=item.fill,
                                 edgecolor="none", linewidth=0))  # fmt: skip
    elif isinstance(item, Line):
        xs, ys = zip(*item.points, strict=True)
        axes.plot(xs, ys, color=item.colour, linewidth=item.width * POINTS_PER_MM,
                  linestyle=(0, (2 / item.width, 1.5 / item.width)) if item.dashed else "-",
                  solid_capstyle="butt")  # fmt: skip
    else:
        axes.text(item.x, item.y, item.text, fontsize=item.size * POINTS_PER_MM,
                  ha={"start": "left", "middle": "center", "end": "right"}[item.anchor],
                  va="baseline", rotation=-item.rotate, rotation_mode="anchor",
                  fontweight="bold" if item.bold else "normal")  # fmt: skip


def write_sheets(
    workcell: Workcell, title: str, out: Path, paper: str
) -> tuple[list[Path], Tiling]:
    """The tiled pages of `workcell`'s sheet: OUT.pdf as one file, OUT.svg as OUT_p1.svg,
    OUT_p2.svg, ...; the files written and the tiling."""
    if paper not in PAPERS:
        raise SheetError(f"paper: one of {sorted(PAPERS)}")
    tiling = tile(workcell, PAPERS[paper])
    made = pages(workcell, tiling, title)
    suffix = out.suffix.lower()
    if suffix == ".pdf":
        write_pdf(made, out)
        return [out], tiling
    if suffix != ".svg":
        raise SheetError(f"{out.name}: give a .pdf (one file) or an .svg (one file a page)")
    paths = []
    for i, page in enumerate(made, 1):
        path = out.with_name(f"{out.stem}_p{i}.svg")
        path.write_text(page_svg(page))
        paths.append(path)
    return paths, tiling


def instructions(workcell: Workcell, tiling: Tiling) -> list[str]:
    """How to print the pages and lay them out, for the command's output."""
    paper = f"{tiling.paper.name} {'landscape' if tiling.landscape else 'portrait'}"
    marked = [t for t in tiling.tiles if t.markers]
    lines = [
        f"{len(tiling.tiles)} pages, {paper}: {tiling.rows} rows x {tiling.cols} columns; row 1 is "
        "the far side of the table (away from the camera), column 1 the left.",
        "Print at 100% (actual size, no 'fit to page'); the 100 mm bar on every page must "
        "measure 100 mm.",
        "Cut each page along its dashed edges (the crop marks show its corners) and butt the "
        "pages edge to edge, each 'joins here' tick meeting its neighbour's; tape from behind.",
        "Or print only the pages with markers and place each marker by its centre in table mm "
        "(printed under it), the page's top edge away from the camera:",
    ]
    for t in marked:
        ids = ", ".join(str(i) for i in t.markers)
        lines.append(f"  page {t.number} (row {t.row}, column {t.col}): marker {ids}")
    lines.append("Check the places with a tape, centre to centre (sides and diagonals):")
    for a, b in itertools.combinations(workcell.markers, 2):
        d = math.dist(a.centre_mm, b.centre_mm)
        lines.append(f"  marker {a.id} to marker {b.id}: {d:.1f} mm")
    return lines
