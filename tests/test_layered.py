"""Analytic layered material: white furnace, energy bound over the prior, sampling vs pdf, live lobes, gradients,
and the shipped albedo tables.

Monte Carlo albedos use the material's own importance sampling (estimator f cos / pdf) and carry their standard
error (SE); "within 4 SE" fails a correct implementation with probability 6e-5 per statistic. TABLE_TOL bounds
the error of the tabulated albedos that energy scaling relies on (quadrature <= 1.1e-3 plus interpolation, up to
~3e-3 at grazing angles; see albedo_tables), so energy statements hold up to 4 SE + TABLE_TOL.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from neumatex_core.materials import albedo_tables as tables
from neumatex_core.materials.base import luminance
from neumatex_core.materials.layered import INDEX, N_PARAMS, PARAMETER_NAMES, LayeredMaterial
from neumatex_core.materials.prior import FAMILIES, sample_base_color, sample_parameters

TABLE_TOL = 5e-3
COS_O = (0.95, 0.6, 0.3, 0.08)


def white(**values: float) -> torch.Tensor:
    """[22] a non-absorbing parameter vector: colours, tints and dust albedo white, everything else 0."""
    p = torch.zeros(N_PARAMS)
    for name in ("dust_albedo", "fuzz_color_r", "fuzz_color_g", "fuzz_color_b", "coat_tint_r", "coat_tint_g",
                 "coat_tint_b"):
        p[INDEX[name]] = 1.0
    for name, v in values.items():
        p[INDEX[name]] = v
    return p


WHITE_F0 = {"spec_f0_r": 1.0, "spec_f0_g": 1.0, "spec_f0_b": 1.0}
DIELECTRIC = {"spec_f0_r": 0.04, "spec_f0_g": 0.04, "spec_f0_b": 0.04}
FURNACE_SETS = {
    "lambert": white(),
    "white_conductor": white(spec_roughness=0.3, **WHITE_F0),
    "coated_plastic": white(coat_weight=1.0, coat_roughness=0.05, coat_ior=0.3, spec_roughness=0.5, **DIELECTRIC),
    "dust_fuzz_scatter": white(dust_coverage=0.5, dust_backscatter=0.7, fuzz_weight=0.8, fuzz_roughness=0.0,
                               scatter_weight=0.7, scatter_anisotropy=0.9),
    "hazy_fuzzy": white(haze_weight=0.5, haze_spread=0.5, spec_roughness=0.1, fuzz_weight=1.0, fuzz_roughness=1.0,
                        spec_f0_r=0.9, spec_f0_g=0.9, spec_f0_b=0.9),
}


def outgoing(cos_o: torch.Tensor) -> torch.Tensor:
    """[N, 3] wo in the xz-plane with cos(theta_o) = cos_o [N]."""
    return torch.stack([torch.sqrt(1 - cos_o * cos_o), torch.zeros_like(cos_o), cos_o], dim=-1)


def mc_albedo(m: LayeredMaterial, wo: torch.Tensor, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per point of m (K points, wo [K, 3]): MC directional albedo [K, 3] and its SE [K, 3] from n samples each."""
    k = wo.shape[0]
    g = torch.Generator().manual_seed(seed)
    idx = torch.arange(k).repeat_interleave(n)
    mm, wo_n = m.select(idx), wo[idx]
    wi, pdf = mm.sample(wo_n, torch.rand(k * n, generator=g), torch.rand(k * n, 2, generator=g))
    with torch.no_grad():
        f = mm.eval(wi, wo_n)
    w = torch.where((pdf > 0).unsqueeze(-1), f * wi[:, 2:3].clamp_min(0) / pdf.clamp_min(1e-30).unsqueeze(-1),
                    torch.zeros_like(f)).double().reshape(k, n, 3)
    return w.mean(1), w.std(1) / math.sqrt(n)


def prior_materials(per_family: int, seed: int) -> tuple[LayeredMaterial, list[str]]:
    g = torch.Generator().manual_seed(seed)
    params, colors, names = [], [], []
    for family in FAMILIES:
        params.append(sample_parameters(family, per_family, g))
        colors.append(torch.rand(per_family, 3, generator=g))  # any rho_d in [0, 1], not only the family's
        names += [family] * per_family
    return LayeredMaterial(torch.cat(params), torch.cat(colors)), names


def test_parameter_list() -> None:
    assert len(PARAMETER_NAMES) == 22 == N_PARAMS and len(set(PARAMETER_NAMES)) == 22
    g = torch.Generator().manual_seed(0)
    for family in FAMILIES:
        p, c = sample_parameters(family, 64, g), sample_base_color(family, 64, g)
        assert p.shape == (64, 22) and c.shape == (64, 3)
        assert bool((p >= 0).all() and (p <= 1).all() and (c >= 0).all() and (c <= 1).all()), family
    with pytest.raises(ValueError):
        sample_parameters("velvet", 1, g)


def test_white_furnace() -> None:
    """Non-absorbing settings with rho_d = 1 reflect all energy: albedo 1 within 1% for every wo."""
    params = torch.stack(list(FURNACE_SETS.values())).repeat_interleave(len(COS_O), 0)
    cos_o = torch.tensor(COS_O).repeat(len(FURNACE_SETS))
    m = LayeredMaterial(params, torch.ones(params.shape[0], 3))
    mean, se = mc_albedo(m, outgoing(cos_o), 100_000, seed=1)
    table_albedo = m.albedo(outgoing(cos_o)).double()
    for i, name in enumerate(np.repeat(list(FURNACE_SETS), len(COS_O))):
        assert float(se[i].max()) < 2.5e-3, (name, se[i])  # the test can resolve 1%
        assert float((mean[i] - 1).abs().max()) < 0.01, (name, float(cos_o[i]), mean[i])
        assert torch.allclose(table_albedo[i], torch.ones(3, dtype=torch.float64), atol=1e-5), table_albedo[i]


def test_energy_bound_over_prior() -> None:
    """200 materials from every family with any rho_d: albedo <= 1 (+ 4 SE + TABLE_TOL); albedo() agrees with MC."""
    m, names = prior_materials(25, seed=2)
    g = torch.Generator().manual_seed(3)
    wo = outgoing(torch.rand(len(names), generator=g) * 0.98 + 0.02)
    mean, se = mc_albedo(m, wo, 10_000, seed=4)
    bound = 1 + 4 * se + TABLE_TOL
    worst = int(torch.argmax((mean - bound).max(-1).values))
    assert bool((mean <= bound).all()), (names[worst], mean[worst], se[worst])
    predicted = m.albedo(wo).double()
    err = (predicted - mean).abs() - 4 * se - 2 * TABLE_TOL
    worst = int(torch.argmax(err.max(-1).values))
    assert bool((err <= 0).all()), (names[worst], predicted[worst], mean[worst], se[worst])


def test_eval_nonnegative_and_components_bounded() -> None:
    m, _ = prior_materials(250, seed=5)
    g = torch.Generator().manual_seed(6)
    n = m.params.shape[0]
    wi = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    f = m.eval(wi, wo)
    assert bool(torch.isfinite(f).all() and (f >= 0).all())
    below = (wi[:, 2] <= 0) | (wo[:, 2] <= 0)
    assert bool((f[below] == 0).all())
    f_spec, t, r = m.components(wi, wo)
    assert bool((f_spec >= 0).all() and (t >= 0).all() and (t <= 1).all() and (r >= 0).all() and (r <= 1).all())
    assert torch.allclose(f, torch.where(below.unsqueeze(-1), 0.0, t * m.base_color / math.pi + f_spec))


LOBE_SWITCHES = {
    "dust": {"dust_coverage": 0.8},
    "fuzz": {"fuzz_weight": 1.0, "fuzz_color_r": 0.9},
    "coat": {"coat_weight": 1.0, "coat_roughness": 0.2, "coat_ior": 1.0},
    "spec": {"spec_f0_r": 0.9, "spec_f0_g": 0.7, "spec_f0_b": 0.5, "spec_roughness": 0.4},
    "haze": {"spec_f0_r": 0.9, "spec_f0_g": 0.7, "spec_f0_b": 0.5, "spec_roughness": 0.1, "haze_weight": 0.8,
             "haze_spread": 0.6},
    "scatter": {"scatter_weight": 0.9, "scatter_anisotropy": 0.9},
}


@pytest.mark.parametrize("lobe", list(LOBE_SWITCHES))
def test_every_lobe_is_live(lobe: str) -> None:
    """Switching one lobe on changes both the BSDF and its albedo (no dead lobe); for haze, relative to spec."""
    base = white(**LOBE_SWITCHES["spec"]) if lobe == "haze" else white()
    on = white(**LOBE_SWITCHES[lobe])
    g = torch.Generator().manual_seed(7)
    n = 4096
    wi = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1).abs()
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1).abs()
    rho = torch.full((n, 3), 0.5)
    f_off = LayeredMaterial(base.expand(n, -1), rho).eval(wi, wo)
    f_on = LayeredMaterial(on.expand(n, -1), rho).eval(wi, wo)
    rel = (f_on - f_off).abs().mean() / f_off.abs().mean()
    assert float(rel) > 0.05, (lobe, float(rel))


def test_sample_pdf_consistency() -> None:
    m, _ = prior_materials(64, seed=8)
    n = m.params.shape[0]
    g = torch.Generator().manual_seed(9)
    wo = outgoing(torch.rand(n, generator=g) * 0.9 + 0.05)
    wi, pdf = m.sample(wo, torch.rand(n, generator=g), torch.rand(n, 2, generator=g))
    assert torch.allclose(pdf, m.pdf(wi, wo), rtol=1e-5, atol=0)
    ok = pdf > 0
    assert bool((wi[ok, 2] > 0).all()) and float(ok.float().mean()) > 0.9
    assert bool((m.select(ok).eval(wi[ok], wo[ok]) >= 0).all())


# Quadrature over the hemisphere in (t, phi) with cos(theta) = t^2: d omega = 2 t dt dphi.
QUAD_T, QUAD_PHI = 1024, 512
CHI_T, CHI_PHI = 8, 16


def quadrature(cos_o: float, m1: LayeredMaterial) -> tuple[torch.Tensor, torch.Tensor]:
    """Cell pdf masses [QUAD_T, QUAD_PHI] and the cell directions' bins (flattened chi-square bin index)."""
    t = (torch.arange(QUAD_T, dtype=torch.float64) + 0.5) / QUAD_T
    phi = (torch.arange(QUAD_PHI, dtype=torch.float64) + 0.5) / QUAD_PHI * 2 * math.pi
    tt, pp = torch.meshgrid(t, phi, indexing="ij")
    mu = tt * tt
    s = torch.sqrt(1 - mu * mu)
    wi = torch.stack([s * torch.cos(pp), s * torch.sin(pp), mu], dim=-1).reshape(-1, 3)
    wo = outgoing(torch.full((wi.shape[0],), cos_o, dtype=torch.float64))
    mm = LayeredMaterial(m1.params.double().expand(wi.shape[0], -1), m1.base_color.double().expand(wi.shape[0], -1))
    mass = mm.pdf(wi, wo) * (2 * tt).reshape(-1) * (1 / QUAD_T) * (2 * math.pi / QUAD_PHI)
    bins = ((tt * CHI_T).long() * CHI_PHI + (pp / (2 * math.pi) * CHI_PHI).long()).reshape(-1)
    return mass, bins


CHI_SETS = {
    "plastic": white(spec_roughness=0.4, **DIELECTRIC),
    "coated_metal": white(coat_weight=1.0, coat_roughness=0.3, spec_roughness=0.5, **WHITE_F0),
    "everything": white(dust_coverage=0.3, dust_backscatter=0.8, fuzz_weight=0.7, coat_weight=0.6,
                        coat_roughness=0.35, spec_roughness=0.3, haze_weight=0.5, haze_spread=0.5,
                        scatter_weight=0.5, scatter_anisotropy=0.2, **WHITE_F0),
}


@pytest.mark.parametrize("name", list(CHI_SETS))
@pytest.mark.parametrize("cos_o", (0.9, 0.3))
def test_pdf_integrates_to_one_and_matches_samples(name: str, cos_o: float) -> None:
    """The pdf integrates to 1 - (rejected mass) (quadrature); samples follow it (chi-square, 8 x 16 bins)."""
    m1 = LayeredMaterial(CHI_SETS[name].unsqueeze(0), torch.full((1, 3), 0.5))
    mass, bins = quadrature(cos_o, m1)
    total = float(mass.sum())
    # VNDF samples that land below the surface are rejected (pdf 0), so the integral is <= 1; the shortfall is
    # checked against the rejection rate below.
    assert 0.9 < total < 1 + 2e-3, total
    expected_p = torch.zeros(CHI_T * CHI_PHI, dtype=torch.float64).index_add(0, bins, mass)
    n = 50_000
    g = torch.Generator().manual_seed(10)
    mm = m1.select(torch.zeros(n, dtype=torch.long))
    wi, pdf = mm.sample(outgoing(torch.full((n,), cos_o)), torch.rand(n, generator=g), torch.rand(n, 2, generator=g))
    valid = pdf > 0
    t = wi[valid, 2].double().clamp(0, 1).sqrt()
    phi = torch.atan2(wi[valid, 1].double(), wi[valid, 0].double()) % (2 * math.pi)
    b = ((t * CHI_T).long().clamp(max=CHI_T - 1) * CHI_PHI + (phi / (2 * math.pi) * CHI_PHI).long().clamp(
        max=CHI_PHI - 1))
    observed = torch.bincount(b, minlength=CHI_T * CHI_PHI).double()
    expected = expected_p / expected_p.sum() * observed.sum()
    keep = expected > 5
    chi2 = float((((observed - expected) ** 2) / expected)[keep].sum())
    p_value = float(stats.chi2.sf(chi2, int(keep.sum()) - 1))
    assert p_value > 1e-4, (name, cos_o, chi2, p_value)
    # The rejected mass (samples below the surface) matches the pdf's missing integral.
    assert abs(float(valid.double().mean()) - total) < 4 * math.sqrt(total * (1 - total) / n) + 2e-3


def test_gradients_flow_to_every_parameter() -> None:
    g = torch.Generator().manual_seed(11)
    n = 512
    params = (torch.rand(n, N_PARAMS, generator=g) * 0.8 + 0.1).requires_grad_(True)
    rho = torch.rand(n, 3, generator=g).requires_grad_(True)
    m = LayeredMaterial(params, rho)
    wo = outgoing(torch.rand(n, generator=g) * 0.9 + 0.1)
    wi, _ = m.sample(wo, torch.rand(n, generator=g), torch.rand(n, 2, generator=g))
    loss = m.eval(wi, wo).sum() + luminance(m.albedo(wo)).sum()
    loss.backward()
    assert params.grad is not None and rho.grad is not None
    assert bool(torch.isfinite(params.grad).all() and torch.isfinite(rho.grad).all())
    dead = [PARAMETER_NAMES[i] for i in range(N_PARAMS) if float(params.grad[:, i].abs().max()) == 0]
    assert not dead, dead


def test_select() -> None:
    m, _ = prior_materials(4, seed=12)
    idx = torch.tensor([3, 0, 7])
    wo = outgoing(torch.tensor([0.5, 0.7, 0.9]))
    direct = LayeredMaterial(m.params[idx], m.base_color[idx])
    assert torch.equal(m.select(idx).albedo(wo), direct.albedo(wo))
    mask = torch.zeros(m.params.shape[0], dtype=torch.bool)
    mask[idx] = True
    assert m.select(mask).params.shape == (3, N_PARAMS)


def test_shipped_tables_reproduce() -> None:
    """Regenerating random cells of every shipped table gives the stored values (up to float32 rounding)."""
    g = torch.Generator().manual_seed(13)
    for name in tables.TABLE_NAMES:
        cells = tables.table_cells(name)
        pick = torch.randint(0, cells[0].shape[0], (12,), generator=g)
        fresh = tables.compute_cells(name, tuple(c[pick] for c in cells))
        stored = torch.as_tensor(tables._load_numpy()[name]).reshape(-1)[pick].double()
        assert torch.allclose(fresh, stored, rtol=1e-5, atol=1e-6), name
        assert tables.table(name, torch.device("cpu")).shape == tables.table_shape(name)


def test_lookup_interpolates_nodes_and_is_differentiable() -> None:
    mu = tables.mu_nodes()[[3, 20]]
    p = tables.param_nodes(tables.P_PARAM)[[5, 30]].clone().requires_grad_(True)
    stored = torch.as_tensor(tables._load_numpy()["fuzz"], dtype=torch.float64)
    value = tables.lookup("fuzz", mu, p)
    assert torch.allclose(value, stored[[3, 20], [5, 30]])
    value.sum().backward()
    assert p.grad is not None and bool((p.grad != 0).all())


@pytest.fixture(scope="module")
def sphere_scene_parts(shared_data):  # type: ignore[no-untyped-def]
    from neumatex_core.geometry.mesh import icosphere
    from neumatex_core.lighting.envmap import EnvironmentMap

    return icosphere(3), EnvironmentMap.from_file(shared_data / "envmaps" / "courtyard.exr")


def _sphere_image(parts, params: torch.Tensor, seed: int) -> torch.Tensor:  # type: ignore[no-untyped-def]
    from neumatex_core.materials.field import UniformLayered
    from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
    from neumatex_core.render.scene import Scene
    from neumatex_core.render.views import sphere_camera

    mesh, env = parts
    scene = Scene(mesh, env, UniformLayered(params, (0.5, 0.5, 0.5)))
    tracer = PathTracer(PathTracerConfig(max_bounces=2, spp=128, hide_background=True))
    with torch.no_grad():
        return tracer.render(scene, sphere_camera(24), seed=seed)


@pytest.mark.parametrize("lobe", list(LOBE_SWITCHES))
def test_every_lobe_changes_the_rendered_sphere(lobe: str, sphere_scene_parts) -> None:  # type: ignore[no-untyped-def]
    """Path-traced sphere under courtyard: switching one lobe on changes the image far beyond Monte Carlo noise.

    Compared on 4x4-pixel block means (the lobes change shading smoothly; blocks average the sun's fireflies).
    The noise scale is the mean |difference| of the same material rendered with two seeds; the lobe's effect
    must exceed it 3x (a dead lobe gives a ratio ~1).
    """
    base = white(**LOBE_SWITCHES["spec"]) if lobe == "haze" else white()
    on = white(**LOBE_SWITCHES[lobe])
    off_a = _sphere_image(sphere_scene_parts, base, seed=1)
    off_b = _sphere_image(sphere_scene_parts, base, seed=2)
    on_c = _sphere_image(sphere_scene_parts, on, seed=3)
    def blocks(img: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.avg_pool2d(img.permute(2, 0, 1).unsqueeze(0), 4)

    noise = (blocks(off_a) - blocks(off_b)).abs().mean()
    effect = (blocks(on_c) - blocks(off_a)).abs().mean()
    assert float(effect) > 3 * float(noise), (lobe, float(effect), float(noise))
