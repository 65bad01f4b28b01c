"""Top-down (bird's-eye view) pictures of a map, and the raster helpers they share.

The picture is a raster, not a scatter: every (x, y) cell of a `TopDownGrid` gets the label
of the highest labelled thing above it (a voxel with evidence for the map, a point for
`compare.py`), found with one lexsort over all items. This stays fast and exact for millions
of voxels, where a scatter plot would be slow and would let draw order decide what is seen.

Matplotlib is used through `matplotlib.figure.Figure` directly: that renders with Agg and
needs no display, without switching the process-wide backend (`matplotlib.use`) under an
application that imported tisem and uses pyplot itself.

`render_bev` writes the map's placement into the PNG as a text chunk (`tisem:bev`, JSON:
cell size, world corner, cell counts, on-screen zoom and the map's pixel box), so a world
(x, y) can be located in the picture: column = left_px + (x - x0) / pixel_m * zoom,
row = top_px + (y0 + height * pixel_m - y) / pixel_m * zoom.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass

import numpy as np
from matplotlib import patheffects
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from tisem.labels import class_colors, class_names
from tisem.snapshot import MapSnapshot

__all__ = [
    "render_bev",
    "TopDownGrid",
    "top_labels",
    "colorize",
    "draw_label_image",
    "draw_trajectory",
    "add_scale_bar",
    "legend_handles",
    "EMPTY",
    "BACKGROUNDS",
    "PNG_KEY",
]

EMPTY = -1  # label image value of a cell with nothing in it
BACKGROUNDS = {"white": (255, 255, 255), "black": (0, 0, 0)}
PNG_KEY = "tisem:bev"
_DPI = 100  # figure inches <-> pixels; the layout below is in pixels
_TARGET_PX = 800  # small maps are enlarged (integer zoom) to about this size
_MAX_ZOOM = 8


@dataclass(frozen=True)
class TopDownGrid:
    """A regular grid of `pixel_m` cells in the world x-y plane; cell (0, 0) starts at (x0, y0)."""

    x0: float
    y0: float
    pixel_m: float
    width: int
    height: int

    @classmethod
    def covering(
        cls, xmin: float, ymin: float, xmax: float, ymax: float, pixel_m: float
    ) -> TopDownGrid:
        """The smallest grid with edges on multiples of `pixel_m` that covers the box.

        Edges on multiples of `pixel_m` mean that when `pixel_m` is a multiple of the voxel size,
        every voxel column falls inside exactly one cell (no aliasing between neighbours).
        """
        # the tolerance keeps a box of exactly n cells (10 m / 0.2 m) from gaining a spurious
        # empty row or column through float rounding
        eps = 1e-9
        i0, j0 = math.floor(xmin / pixel_m + eps), math.floor(ymin / pixel_m + eps)
        i1, j1 = math.ceil(xmax / pixel_m - eps), math.ceil(ymax / pixel_m - eps)
        return cls(i0 * pixel_m, j0 * pixel_m, float(pixel_m), max(1, i1 - i0), max(1, j1 - j0))

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(left, right, bottom, top) in metres, as imshow's `extent` wants it."""
        return (
            self.x0,
            self.x0 + self.width * self.pixel_m,
            self.y0,
            self.y0 + self.height * self.pixel_m,
        )

    def cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat cell index (row-major, row 0 = lowest y) of each (x, y), and which are inside."""
        ix = np.floor((xy[:, 0] - self.x0) / self.pixel_m).astype(np.int64)
        iy = np.floor((xy[:, 1] - self.y0) / self.pixel_m).astype(np.int64)
        inside = (ix >= 0) & (ix < self.width) & (iy >= 0) & (iy < self.height)
        return iy * self.width + ix, inside


def top_labels(grid: TopDownGrid, xy: np.ndarray, z: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(height, width) int32 image: per cell the label of the highest item in it, else EMPTY.

    Row 0 is the lowest y (draw with `origin="lower"`). Items outside the grid are ignored.
    """
    flat, inside = grid.cells(np.asarray(xy, dtype=np.float64))
    flat, z, labels = flat[inside], np.asarray(z)[inside], np.asarray(labels)[inside]
    image = np.full(grid.width * grid.height, EMPTY, dtype=np.int32)
    if flat.size:
        order = np.lexsort((z, flat))  # by cell, then by height within the cell
        flat_sorted = flat[order]
        highest = np.r_[flat_sorted[1:] != flat_sorted[:-1], True]  # last item of each cell
        image[flat_sorted[highest]] = labels[order][highest]
    return image.reshape(grid.height, grid.width)


def colorize(label_image: np.ndarray, background: str = "white") -> np.ndarray:
    """(H, W) labels -> (H, W, 3) uint8 SemanticKITTI colours; EMPTY cells get the background."""
    if background not in BACKGROUNDS:
        raise ValueError(f"background must be one of {sorted(BACKGROUNDS)}, got {background!r}")
    rgb = np.empty(label_image.shape + (3,), dtype=np.uint8)
    rgb[...] = BACKGROUNDS[background]
    filled = label_image != EMPTY
    rgb[filled] = class_colors()[label_image[filled]]
    return rgb


def draw_label_image(
    ax, grid: TopDownGrid, label_image: np.ndarray, background: str = "white"
) -> None:
    """Show a label image on `ax` in world metres, one image pixel per grid cell."""
    ax.imshow(
        colorize(label_image, background),
        origin="lower",
        extent=grid.extent,
        interpolation="nearest",
        aspect="equal",
    )
    left, right, bottom, top = grid.extent
    ax.set_xlim(left, right)
    ax.set_ylim(bottom, top)


def legend_handles(labels_present) -> list:
    """Colour patches with class names for the given train ids, in train id order."""
    colors, names = class_colors(), class_names()
    return [
        Patch(
            facecolor=colors[c] / 255.0,
            edgecolor="0.4",
            linewidth=0.5,
            label=f"{int(c):2d} {names[c]}",
        )
        for c in sorted(set(labels_present))
    ]


def _nice_length(max_m: float) -> float:
    """The largest 1, 2 or 5 x 10^k not above `max_m` (a readable scale bar length)."""
    if max_m <= 0:
        return 1.0
    base = 10.0 ** math.floor(math.log10(max_m))
    return max(m * base for m in (1, 2, 5) if m * base <= max_m)


def add_scale_bar(ax, width_m: float, background: str = "white", loc: str = "lower left") -> float:
    """Draw a scale bar of about a fifth of the view's width; returns its length in metres."""
    length = _nice_length(width_m / 5.0)
    ink = "black" if background == "white" else "white"
    bar = AnchoredSizeBar(
        ax.transData,
        length,
        f"{length:g} m",
        loc=loc,
        pad=0.3,
        borderpad=0.6,
        sep=3,
        color=ink,
        frameon=True,
        size_vertical=width_m / 250.0,
    )
    bar.patch.set_facecolor(background)
    bar.patch.set_alpha(0.75)
    bar.patch.set_edgecolor("0.5")
    ax.add_artist(bar)
    return length


def draw_trajectory(ax, trajectory_xy) -> list:
    """The sensor path as a line with start and end markers; returns legend handles."""
    xy = np.asarray(trajectory_xy, dtype=np.float64).reshape(-1, 2)
    xy = xy[np.isfinite(xy).all(axis=1)]
    if not len(xy):
        return []
    halo = [patheffects.withStroke(linewidth=3.5, foreground="white")]  # visible on any class
    ax.plot(xy[:, 0], xy[:, 1], color="black", linewidth=1.5, path_effects=halo, zorder=3)
    ax.plot(
        *xy[0], marker="o", markersize=9, markerfacecolor="lime", markeredgecolor="black", zorder=4
    )
    ax.plot(
        *xy[-1], marker="s", markersize=8, markerfacecolor="red", markeredgecolor="black", zorder=4
    )
    return [
        Line2D([], [], color="black", linewidth=1.5, label="trajectory"),
        Line2D(
            [],
            [],
            linestyle="none",
            marker="o",
            markerfacecolor="lime",
            markeredgecolor="black",
            label="start",
        ),
        Line2D(
            [],
            [],
            linestyle="none",
            marker="s",
            markerfacecolor="red",
            markeredgecolor="black",
            label="end",
        ),
    ]


def _choose_pixel(
    snapshot_res: float, span_m: float, pixel_m: float | None, max_pixels: int
) -> float:
    """Cell size: the voxel size (or `pixel_m`), coarsened to a whole multiple of it if the
    longer side would exceed `max_pixels` cells."""
    base = float(pixel_m) if pixel_m else float(snapshot_res)
    if base <= 0:
        raise ValueError(f"pixel size must be > 0, got {base}")
    factor = max(1, math.ceil(span_m / base / max_pixels - 1e-9))
    return base * factor


def render_bev(
    snapshot: MapSnapshot,
    path: str | os.PathLike,
    trajectory_xy=None,
    title: str | None = None,
    pixel_m: float | None = None,
    max_pixels: int = 2000,
    background: str = "white",
) -> float:
    """Write a top-down PNG of the map coloured by class; returns the cell size used (metres).

    Each (x, y) cell shows the label of the highest voxel with evidence above it; cells without
    any show `background` ("white" or "black"). With a legend of the classes present, a scale
    bar, and `trajectory_xy` ((T, 2) sensor positions) drawn as a line with start/end markers.
    The cell size is `pixel_m` (default: the voxel size), made a whole multiple coarser when
    the map's longer side would need more than `max_pixels` cells.
    """
    if max_pixels < 1:
        raise ValueError(f"max_pixels must be >= 1, got {max_pixels}")
    res = float(snapshot.resolution_m)
    has_evidence = snapshot.counts.sum(axis=1) > 0 if len(snapshot) else np.zeros(0, bool)
    centers = snapshot.centers()[has_evidence]
    labels = snapshot.labels()[has_evidence]
    traj = (
        None
        if trajectory_xy is None
        else np.asarray(trajectory_xy, dtype=np.float64).reshape(-1, 2)
    )

    # the view covers the voxels' columns (centre +- half a voxel) and the whole trajectory
    lo, hi = [], []
    if len(centers):
        lo.append(centers[:, :2].min(axis=0) - res / 2)
        hi.append(centers[:, :2].max(axis=0) + res / 2)
    if traj is not None and np.isfinite(traj).all(axis=1).any():
        finite = traj[np.isfinite(traj).all(axis=1)]
        lo.append(finite.min(axis=0) - 2 * res)
        hi.append(finite.max(axis=0) + 2 * res)
    if lo:
        lo_xy, hi_xy = np.min(lo, axis=0), np.max(hi, axis=0)
    else:  # nothing to show: a small empty square at 0
        lo_xy, hi_xy = np.array([-res, -res]), np.array([res, res])
    cell = _choose_pixel(res, float(np.max(hi_xy - lo_xy)), pixel_m, max_pixels)
    grid = TopDownGrid.covering(lo_xy[0], lo_xy[1], hi_xy[0], hi_xy[1], cell)
    image = top_labels(grid, centers[:, :2], centers[:, 2], labels)

    # pixel layout: the map at an integer zoom, a legend column on the right, title on top
    zoom = int(min(_MAX_ZOOM, max(1, _TARGET_PX // max(grid.width, grid.height))))
    map_w, map_h = grid.width * zoom, grid.height * zoom
    present = np.unique(image[image != EMPTY])
    handles = legend_handles(present)
    pad, legend_w = 16, 200
    top = 40 if title else pad
    legend_h = 22 * (len(handles) + 3) + 120  # entries + trajectory + caption
    fig_w = pad + map_w + pad + legend_w
    fig_h = max(top + map_h + pad, legend_h)
    # a hair over the exact size so that float inches * dpi never truncates a pixel away
    fig = Figure(
        figsize=((fig_w + 1e-3) / _DPI, (fig_h + 1e-3) / _DPI), dpi=_DPI, facecolor="white"
    )
    ax = fig.add_axes((pad / fig_w, (fig_h - top - map_h) / fig_h, map_w / fig_w, map_h / fig_h))
    draw_label_image(ax, grid, image, background)
    ax.set_xticks([])
    ax.set_yticks([])
    if traj is not None:
        handles += draw_trajectory(ax, traj)
    width_m = grid.width * grid.pixel_m
    bar_m = add_scale_bar(ax, width_m, background)
    if title:
        fig.text(pad / fig_w, 1 - 12 / fig_h, title, ha="left", va="top", fontsize=13)
    legend_x = (pad + map_w + pad) / fig_w
    if handles:
        fig.legend(
            handles=handles,
            loc="upper left",
            bbox_to_anchor=(legend_x, 1 - top / fig_h),
            frameon=False,
            fontsize=9,
            title="classes",
            alignment="left",
            prop={"family": "monospace", "size": 9},
        )
    left, right, bottom, top_m = grid.extent
    caption = (
        f"{len(centers)} voxels with evidence\ncell {grid.pixel_m:g} m, "
        f"bar {bar_m:g} m\nx {left:.1f} .. {right:.1f} m\ny {bottom:.1f} .. {top_m:.1f} m"
    )
    if not len(centers):
        caption = "empty map: no voxel with evidence\n" + caption
    fig.text(legend_x, pad / fig_h, caption, ha="left", va="bottom", fontsize=8, color="0.25")

    georef = dict(asdict(grid), zoom=zoom, left_px=pad, top_px=top, image_w=fig_w, image_h=fig_h)
    fig.savefig(
        os.fspath(path),
        format="png",
        dpi=_DPI,
        metadata={"Software": "tisem", PNG_KEY: json.dumps(georef)},
    )
    return grid.pixel_m
