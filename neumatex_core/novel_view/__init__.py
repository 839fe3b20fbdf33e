"""Novel-view preparation: the 23 preset views from arbitrary photographs on the known mesh."""

from neumatex_core.novel_view.lumigraph import Photo, PreparedViews, blend_views

__all__ = ["Photo", "PreparedViews", "blend_views"]
