"""Whether a capture's photos are the 23 preset views themselves (then prepare_views takes them as they are), and if
not, why not, in one sentence.

A photo counts as preset view k when its camera-to-world matrix equals the preset's (any square resolution) within
`PRESET_TOLERANCE` per entry and its focal length within that fraction. The LMRM reads the preset views exactly as
rendered from those poses (distance 3.2, 40 degree field of view), so a photo in a preset *direction* but at another
distance or zoom is not one: the object would be larger or smaller than the LMRM expects. Such photos are blended
(reprojected onto the mesh) into the preset views instead, which handles any pose; the reason says which check
failed and by how much, so that a capture meant as preset views can be fixed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from neumatex_core.geometry.camera import PRESET_DISTANCE, Camera, preset_views

PRESET_TOLERANCE = 1e-3  # max |c2w difference| (and relative focal difference) for a photo to count as a preset view
PRESET_COUNT = 23


@dataclass
class PresetMatch:
    """frames: the frame index of each preset view, or None; reason: why not (one sentence), "" when matched;
    aimed: how many preset views have a photo at their pose or in their direction (within 0.1 degree): a capture
    with some was probably meant as preset views."""

    frames: list[int] | None
    reason: str = ""
    aimed: int = 0


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    if na == 0 or nb == 0:
        return 180.0
    return math.degrees(math.acos(float(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def _mismatch(cam: Camera, preset: Camera, tol: float) -> str:
    """Why `cam` is not `preset` ("" when it is)."""
    pos, ref = cam.position, preset.position
    dist, ref_dist = float(np.linalg.norm(pos)), float(np.linalg.norm(ref))
    if abs(dist - ref_dist) > tol:
        return f"at distance {dist:.4g} from the origin instead of {ref_dist:.4g} (off by {abs(dist - ref_dist):.3g})"
    rot = float(np.abs(np.asarray(cam.c2w)[:3, :3] - preset.c2w[:3, :3]).max())
    if rot > tol:
        return f"rotated differently (rotation entries differ by up to {rot:.3g})"
    off = float(np.abs(pos - ref).max())
    if off > tol:
        return f"{off:.3g} away from the preset position"
    if abs(cam.fl_x - preset.fl_x) > tol * preset.fl_x:
        return (f"with a focal length of {cam.fl_x:.5g} px instead of {preset.fl_x:.5g} px (field of view "
                f"{cam.fov_x_deg:.3g} instead of {preset.fov_x_deg:.3g} degrees)")
    return ""


def match_preset_views(cameras: list[Camera], tol: float = PRESET_TOLERANCE) -> PresetMatch:
    """The frame of each of the 23 preset views if the photos include them all, else the reason (module doc)."""
    square = [i for i, c in enumerate(cameras) if c.width == c.height]
    if not square:
        return PresetMatch(None, "not taken as the preset views: no photo is square, and the preset views are")
    presets = {cameras[i].width: preset_views(cameras[i].width) for i in square}
    found: list[int] = []
    closest: list[tuple[int, int, float, str]] = []  # (preset, frame, direction angle, mismatch) of unmatched presets
    for k in range(PRESET_COUNT):
        best: tuple[float, int, str] | None = None
        for i in square:
            preset = presets[cameras[i].width][k]
            why = _mismatch(cameras[i], preset, tol)
            if not why:
                best = (0.0, i, "")
                break
            angle = _angle_deg(cameras[i].position, preset.position)
            if best is None or angle < best[0]:
                best = (angle, i, why)
        assert best is not None
        if best[2]:
            closest.append((k, best[1], best[0], best[2]))
        else:
            found.append(best[1])
    in_direction = [c for c in closest if c[2] < 0.1]
    if not closest:
        return PresetMatch(found, "", PRESET_COUNT)
    k, i, angle, why = min(closest, key=lambda c: c[2])
    if len(in_direction) == len(closest):  # every unmatched preset has a photo in its direction: pose details differ
        lead = (f"the photos are in the directions of {len(in_direction)} preset view(s) but not at their poses "
                f"(e.g. frame {i} for preset view {k}: {why}; tolerance {tol:g})")
    else:
        lead = (f"{len(closest)} of the {PRESET_COUNT} preset views have no photo at their pose (e.g. preset view {k}: "
                f"the photo closest in direction, frame {i}, is {angle:.3g} degrees off and {why}; tolerance {tol:g})")
    distance = ""
    if all("at distance" in c[3] for c in closest):
        distance = f"; the preset views are at distance {PRESET_DISTANCE}"
    return PresetMatch(None, f"not taken as the preset views: {lead}{distance}; they are blended into the preset "
                             "views instead (unstructured lumigraph)", len(found) + len(in_direction))
