"""Lighting for synthetic objects: the shared HDR maps under random rotation and exposure, and procedural
sun-and-sky maps.

A `LightingSpec` is what a capture stores: the map file (a shared map copied byte for byte, or a sky rendered by
`sun_sky_map` and written as EXR), `envmap_to_world` (a rotation about +Y by `rotation_deg`) and `envmap_scale`.
The scale normalises the map's mean luminance (solid-angle weighted, the irradiance a grey sphere sees on
average) to `TARGET_LUMINANCE` times 2^`stops`, with `stops` uniform in +-EXPOSURE_STOPS, so objects come out
neither black nor white under the capture's default tonemap (exposure 1, sRGB), whatever the map's units.

The sky: a zenith-to-horizon gradient whose colours warm as the sun sinks, a brighter band and a glow around the
sun, a sun disk of `SUN_RADIUS_DEG` (at 256 x 512 texels the disk covers ~20 texels, which the map's
importance sampling finds) carrying SUN_TO_SKY times the sky's irradiance, and a dim ground of random albedo below
the horizon lit by both. Radiance is linear RGB in the map's own frame (Mitsuba's envmap mapping).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from neumatex_core.imageio import read_image
from neumatex_core.lighting.envmap import LUMINANCE, envmap_rgb

TARGET_LUMINANCE = 0.6
EXPOSURE_STOPS = 0.75
SUN_RADIUS_DEG = 2.5
SKY_HEIGHT = 256


@dataclass(frozen=True)
class LightingSpec:
    """kind "shared" (map = a shared map's file name) or "sky" (sky = `sun_sky_map` keyword arguments);
    rotation_deg about +Y; stops: exposure offset in stops from the normalised brightness."""

    kind: str
    map: str = ""
    rotation_deg: float = 0.0
    stops: float = 0.0
    sky: dict[str, Any] = field(default_factory=dict)


def yaw_rotation(degrees: float) -> np.ndarray:
    """[3, 3] rotation about +Y (the map's `to_world`)."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def mean_luminance(pixels: np.ndarray) -> float:
    """Solid-angle weighted mean luminance of an equirectangular map [H, W, C] (negatives clamped)."""
    rgb = np.maximum(envmap_rgb(pixels).astype(np.float64), 0.0)
    h = rgb.shape[0]
    weight = np.sin(math.pi * (np.arange(h) + 0.5) / h)[:, None]
    lum = rgb @ np.asarray(LUMINANCE)
    return float((lum * weight).sum() / (weight.sum() * rgb.shape[1]))


def _hsv_free_tint(rng: np.random.Generator, base: np.ndarray, spread: float) -> np.ndarray:
    return np.clip(base * (1 + rng.uniform(-spread, spread, 3)), 0.0, None)


def sample_sky(rng: np.random.Generator) -> dict[str, Any]:
    """Keyword arguments of `sun_sky_map` for a random clear or hazy sky."""
    elevation = float(rng.uniform(5.0, 75.0))
    warm = max(0.0, 1 - elevation / 35)  # low sun: warm light, pale sky
    sun = np.array([1.0, 0.95 - 0.25 * warm, 0.88 - 0.45 * warm])
    zenith = _hsv_free_tint(rng, np.array([0.22, 0.38, 0.75]) * (1 - 0.4 * warm), 0.15)
    horizon = _hsv_free_tint(rng, np.array([0.75, 0.8, 0.9]) * (1 - 0.3 * warm) + warm * np.array([0.3, 0.15, 0.0]),
                             0.1)  # fmt: skip
    return {
        "sun_elevation_deg": round(elevation, 4),
        "sun_azimuth_deg": round(float(rng.uniform(0.0, 360.0)), 4),
        "sun_color": sun.round(4).tolist(),
        "sun_to_sky": round(float(rng.uniform(1.5, 6.0)), 4),
        "zenith": zenith.round(4).tolist(),
        "horizon": horizon.round(4).tolist(),
        "ground_albedo": round(float(rng.uniform(0.1, 0.4)), 4),
        "haze": round(float(rng.uniform(0.0, 1.0)), 4),
    }


def sun_sky_map(sun_elevation_deg: float, sun_azimuth_deg: float, sun_color: list[float], sun_to_sky: float,
                zenith: list[float], horizon: list[float], ground_albedo: float, haze: float,
                height: int = SKY_HEIGHT) -> np.ndarray:
    """float32 [height, 2 height, 3] linear sun-and-sky map (see the module docstring)."""
    h, w = height, 2 * height
    v = (np.arange(h) + 0.5) / h
    u = (np.arange(w) + 0.5) / w
    theta = math.pi * v[:, None] * np.ones((1, w))
    phi = 2 * math.pi * u[None, :] * np.ones((h, 1))
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)  # envmap mapping
    el, az = math.radians(sun_elevation_deg), math.radians(sun_azimuth_deg)
    s = np.array([math.cos(el) * math.sin(az), math.sin(el), -math.cos(el) * math.cos(az)])
    up = np.clip(d[..., 1], 0.0, 1.0)
    cos_sun = np.clip(d @ s, -1.0, 1.0)
    angle = np.arccos(cos_sun)
    t = (1 - up) ** (3.0 - 2.0 * haze)
    sky = (1 - t)[..., None] * np.asarray(zenith) + t[..., None] * np.asarray(horizon)
    glow = (0.6 + 1.5 * haze) * np.exp(-angle / (0.12 + 0.25 * haze)) + 0.15 * (1 + cos_sun) ** 2
    sky = sky * (1 + glow[..., None] * np.asarray(sun_color))
    above = d[..., 1] > 0
    # Sky irradiance on an upward surface, then the sun disk scaled to sun_to_sky times it.
    weight = np.sin(theta) * (math.pi / h) * (2 * math.pi / w)
    lum = sky @ np.asarray(LUMINANCE)
    e_sky = float((lum * up * weight * above).sum())
    r = math.radians(SUN_RADIUS_DEG)
    disk = np.clip((r - angle) / (0.25 * r) + 0.5, 0.0, 1.0)  # a disk with a quarter-radius soft edge
    disk_irr = float((disk * weight).sum()) * max(math.sin(el), 0.05)
    sun_radiance = sun_to_sky * e_sky / max(disk_irr, 1e-9)
    radiance = np.where(above[..., None], sky, 0.0) + disk[..., None] * sun_radiance * np.asarray(sun_color)
    ground_irr = e_sky + sun_to_sky * e_sky  # a horizontal ground sees the whole sky and the sun
    ground = ground_albedo / math.pi * ground_irr * np.array([1.0, 0.9, 0.75])
    radiance = np.where(above[..., None] | (disk[..., None] > 0), radiance, ground)
    return radiance.astype(np.float32)


def sample_lighting(rng: np.random.Generator, maps: list[str], p_sky: float, avoid: str = "") -> LightingSpec:
    """A random LightingSpec: a sky with probability p_sky, else one of `maps` (not `avoid` when others exist)."""
    rotation = round(float(rng.uniform(0.0, 360.0)), 4)
    stops = round(float(rng.uniform(-EXPOSURE_STOPS, EXPOSURE_STOPS)), 4)
    if rng.uniform() < p_sky or not maps:
        return LightingSpec("sky", "", rotation, stops, sample_sky(rng))
    choices = [m for m in maps if m != avoid] or maps
    return LightingSpec("shared", str(rng.choice(choices)), rotation, stops)


@lru_cache(maxsize=16)
def _shared_map(path: str) -> np.ndarray:
    return read_image(path)


def lighting_pixels(spec: LightingSpec, envmaps_dir: Path | None) -> np.ndarray:
    """The map's texels as stored in the capture file (float32 [H, W, C], before rotation and scale)."""
    if spec.kind == "sky":
        return sun_sky_map(**spec.sky)
    if envmaps_dir is None:
        raise ValueError("a shared-map lighting needs the envmaps folder")
    return _shared_map(str(Path(envmaps_dir) / spec.map))


def lighting_scale(spec: LightingSpec, pixels: np.ndarray) -> float:
    """envmap_scale: TARGET_LUMINANCE * 2^stops / the map's mean luminance (rounded to 6 significant digits)."""
    return float(f"{TARGET_LUMINANCE * 2.0 ** spec.stops / max(mean_luminance(pixels), 1e-12):.6g}")
