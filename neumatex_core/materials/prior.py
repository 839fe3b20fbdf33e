"""A prior over the layered material's 22 parameters, by material family (for data synthesis and tests).

`sample_parameters(family, n, generator)` draws [n, 22] normalised parameters (order `PARAMETER_NAMES`) of
plausible materials of one family; `sample_base_color` draws matching Lambertian base colours rho_d [n, 3].
Every family starts from a neutral material (no dust, fuzz, coat, haze or scatter; white colours and tints)
and switches on what characterises it:

- plastic: dielectric specular (f0 0.02..0.06, grey), roughness 0.1..0.8, saturated base colour;
- metal: coloured f0 (random hue, value 0.5..1, saturation <= 0.5), roughness 0.1..0.7, dark base (<= 0.05);
- coated: clear coat weight 0.7..1 (roughness 0.1..0.35, some tint) over a plastic or metal;
- dusty: dust coverage 0.3..1 with any back-scatter over a plastic;
- fuzzy: fuzz weight 0.5..1 (cloth-like, rough specular);
- hazy: haze weight 0.3..1 with spread 0.2..1 over a glossy (roughness 0.1..0.35) metal or plastic;
- scattering: scatter weight 0.4..1, any anisotropy, weak specular, light base (skin, wax, marble);
- mixture: every layer switched on independently with probability 1/2, at uniform strengths.

No GGX roughness goes below ROUGHNESS_MIN = 0.1 (alpha 0.01, a peak of ~3e3 / sr): sharper, near-mirror lobes
are beyond what the 4x64 neural basis can represent (and what 17 views under an environment map can pin down).
"""

from __future__ import annotations

import torch

from neumatex_core.materials.layered import INDEX, N_PARAMS

ROUGHNESS_MIN = 0.1
FAMILIES = ("plastic", "metal", "coated", "dusty", "fuzzy", "hazy", "scattering", "mixture")


def _u(n: int, lo: float, hi: float, g: torch.Generator) -> torch.Tensor:
    """[n] uniform in [lo, hi]."""
    return lo + (hi - lo) * torch.rand(n, generator=g)


def _set(p: torch.Tensor, name: str, value: torch.Tensor | float) -> None:
    p[:, INDEX[name]] = value


def _set_rgb(p: torch.Tensor, name: str, value: torch.Tensor) -> None:
    i = INDEX[name + "_r"]
    p[:, i:i + 3] = value


def _hue_color(n: int, sat_lo: float, sat_hi: float, val_lo: float, val_hi: float, g: torch.Generator) -> torch.Tensor:
    """[n, 3] RGB colours of random hue with saturation and value in the given ranges (HSV model)."""
    h = torch.rand(n, generator=g) * 6
    s, v = _u(n, sat_lo, sat_hi, g), _u(n, val_lo, val_hi, g)
    k = (torch.tensor([5.0, 3.0, 1.0]) + h.unsqueeze(-1)) % 6
    return v.unsqueeze(-1) * (1 - s.unsqueeze(-1) * torch.clamp(torch.minimum(k, 4 - k), 0, 1))


def _neutral(n: int) -> torch.Tensor:
    """[n, 22]: every optional layer off, colours and tints white, mid roughness, dielectric f0 0.04."""
    p = torch.zeros(n, N_PARAMS)
    for name in ("fuzz_color", "coat_tint"):
        _set_rgb(p, name, torch.ones(n, 3))
    _set(p, "dust_albedo", 0.8)
    _set(p, "dust_backscatter", 0.5)
    _set(p, "fuzz_roughness", 0.5)
    _set(p, "coat_ior", (1.5 - 1.3) / 0.7)
    _set(p, "spec_roughness", 0.5)
    _set_rgb(p, "spec_f0", torch.full((n, 3), 0.04))
    _set(p, "scatter_anisotropy", 0.5)
    return p


def _plastic(p: torch.Tensor, g: torch.Generator) -> None:
    n = p.shape[0]
    _set_rgb(p, "spec_f0", _u(n, 0.02, 0.06, g).unsqueeze(-1).expand(n, 3))
    _set(p, "spec_roughness", _u(n, 0.1, 0.8, g))


def _metal(p: torch.Tensor, g: torch.Generator) -> None:
    n = p.shape[0]
    _set_rgb(p, "spec_f0", _hue_color(n, 0.0, 0.5, 0.5, 1.0, g))
    _set(p, "spec_roughness", _u(n, ROUGHNESS_MIN, 0.7, g))


def sample_parameters(family: str, n: int, generator: torch.Generator) -> torch.Tensor:
    """[n, 22] normalised layered-material parameters (float32, CPU) of one family of `FAMILIES`."""
    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r}; expected one of {FAMILIES}")
    g = generator
    p = _neutral(n)
    metal = torch.rand(n, generator=g) < 0.5
    if family == "plastic":
        _plastic(p, g)
    elif family == "metal":
        _metal(p, g)
    elif family in ("coated", "hazy"):
        _plastic(p, g)
        q = _neutral(n)
        _metal(q, g)
        p = torch.where(metal.unsqueeze(-1), q, p)
        if family == "coated":
            _set(p, "coat_weight", _u(n, 0.7, 1.0, g))
            _set(p, "coat_roughness", _u(n, ROUGHNESS_MIN, 0.35, g))
            _set(p, "coat_ior", torch.rand(n, generator=g))
            _set_rgb(p, "coat_tint", _hue_color(n, 0.0, 0.4, 0.7, 1.0, g))
        else:
            _set(p, "spec_roughness", _u(n, ROUGHNESS_MIN, 0.35, g))
            _set(p, "haze_weight", _u(n, 0.3, 1.0, g))
            _set(p, "haze_spread", _u(n, 0.2, 1.0, g))
    elif family == "dusty":
        _plastic(p, g)
        _set(p, "dust_coverage", _u(n, 0.3, 1.0, g))
        _set(p, "dust_backscatter", torch.rand(n, generator=g))
        _set(p, "dust_albedo", _u(n, 0.3, 0.9, g))
    elif family == "fuzzy":
        _plastic(p, g)
        _set(p, "spec_roughness", _u(n, 0.5, 0.9, g))
        _set(p, "fuzz_weight", _u(n, 0.5, 1.0, g))
        _set(p, "fuzz_roughness", torch.rand(n, generator=g))
        _set_rgb(p, "fuzz_color", _hue_color(n, 0.0, 0.7, 0.4, 1.0, g))
    elif family == "scattering":
        _plastic(p, g)
        _set(p, "scatter_weight", _u(n, 0.4, 1.0, g))
        _set(p, "scatter_anisotropy", torch.rand(n, generator=g))
    else:  # mixture: each layer on with probability 1/2, all parameters uniform
        p = torch.rand(n, N_PARAMS, generator=g)
        for gate in ("dust_coverage", "fuzz_weight", "coat_weight", "haze_weight", "scatter_weight"):
            on = torch.rand(n, generator=g) < 0.5
            p[:, INDEX[gate]] = torch.where(on, p[:, INDEX[gate]], torch.zeros(n))
        for name in ("coat_roughness", "spec_roughness"):
            p[:, INDEX[name]] = ROUGHNESS_MIN + (1 - ROUGHNESS_MIN) * p[:, INDEX[name]]
    return p


def sample_base_color(family: str, n: int, generator: torch.Generator) -> torch.Tensor:
    """[n, 3] Lambertian base colour rho_d in [0, 1] (linear RGB) matching `family`.

    Metals get a dark base (<= 0.05), scattering materials a light, low-saturation one, the rest any hue with
    value 0.05..0.9 (few real dielectrics are brighter).
    """
    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r}; expected one of {FAMILIES}")
    g = generator
    if family == "metal":
        return _hue_color(n, 0.0, 1.0, 0.0, 0.05, g)
    if family == "scattering":
        return _hue_color(n, 0.0, 0.5, 0.5, 0.9, g)
    return _hue_color(n, 0.0, 1.0, 0.05, 0.9, g)
