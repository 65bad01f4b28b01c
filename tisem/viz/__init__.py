"""Pictures of maps: top-down class maps (`render_bev`) and region comparisons
(`render_comparison`). Rendering uses matplotlib's Agg through `Figure`, never a display."""

from tisem.viz.bev import render_bev
from tisem.viz.compare import render_comparison

__all__ = ["render_bev", "render_comparison"]
