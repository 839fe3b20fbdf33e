"""Environment map: Mitsuba's equirectangular mapping, and an importance sampler whose pdf is exact.

Every tolerance is derived from the quadrature resolution or from the Monte Carlo standard error of the
statistic it bounds (see each test). Each statistical test is also run on a deliberately wrong variant
(the pdf without the sin(theta) Jacobian), which the same statistic must reject, so the tests can fail.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import ENVMAPS
from scipy import stats

from neumatex_core.lighting.envmap import LUMINANCE, EnvironmentMap

N_SAMPLES = 200_000
P_MIN = 1e-3  # chi-square acceptance threshold: a correct sampler fails with probability 1e-3 per seed


def rotation(axis: tuple[float, float, float], degrees: float) -> np.ndarray:
    """Rodrigues rotation matrix [3, 3] about `axis` by `degrees`."""
    a = np.asarray(axis, dtype=np.float64)
    a /= np.linalg.norm(a)
    t = math.radians(degrees)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


OBLIQUE = rotation((1.0, 2.0, 3.0), 40.0)


@pytest.fixture(scope="module")
def sunrise() -> EnvironmentMap:
    """A shared map with a sun (peak ~35,000): the hard case for importance sampling."""
    return EnvironmentMap.from_file(ENVMAPS / "sunrise.exr")


@pytest.fixture(scope="module")
def sunrise_rotated(sunrise: EnvironmentMap) -> EnvironmentMap:
    return EnvironmentMap(sunrise.texels.numpy(), OBLIQUE)


@pytest.fixture(scope="module")
def courtyard_rotated() -> EnvironmentMap:
    """A shared map without a sun (peak ~55), rotated: smooth enough for an accurate world-frame
    quadrature."""
    base = EnvironmentMap.from_file(ENVMAPS / "courtyard.exr")
    return EnvironmentMap(base.texels.numpy(), OBLIQUE)


def uv_grid(nu: int, nv: int, v0: int = 0, v1: int | None = None) -> torch.Tensor:
    """Midpoints [n, 2] of an nu x nv grid over [0, 1)^2 (rows v0..v1 only), row-major in v."""
    v1 = nv if v1 is None else v1
    u = (torch.arange(nu, dtype=torch.float64) + 0.5) / nu
    v = (torch.arange(v0, v1, dtype=torch.float64) + 0.5) / nv
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu, vv], dim=-1).reshape(-1, 2)


def equal_area_directions(nphi: int, nz: int, z0: int = 0, z1: int | None = None) -> torch.Tensor:
    """World directions [n, 3] at the midpoints of an nphi x nz grid in (phi, cos theta): every point
    stands for the same solid angle 4 pi / (nphi nz). Row-major in z (rows z0..z1 only)."""
    z1 = nz if z1 is None else z1
    phi = (torch.arange(nphi, dtype=torch.float64) + 0.5) / nphi * 2 * math.pi
    z = 1 - 2 * (torch.arange(z0, z1, dtype=torch.float64) + 0.5) / nz
    zz, pp = torch.meshgrid(z, phi, indexing="ij")
    s = torch.sqrt(1 - zz * zz)
    return torch.stack([s * torch.sin(pp), zz, -s * torch.cos(pp)], dim=-1).reshape(-1, 3)


def world_bin(directions: torch.Tensor, nphi: int, nz: int) -> torch.Tensor:
    """Index [n] of the equal-area world bin (nphi x nz over (phi, cos theta), row-major in z)."""
    d = directions.double()
    phi = torch.atan2(d[:, 0], -d[:, 2]) % (2 * math.pi)
    col = (phi / (2 * math.pi) * nphi).long().clamp(0, nphi - 1)
    row = ((1 - d[:, 1].clamp(-1, 1)) / 2 * nz).long().clamp(0, nz - 1)
    return row * nphi + col


def chi_square_p(counts: np.ndarray, expected: np.ndarray, min_expected: float = 5.0) -> float:
    """Pearson chi-square p-value; bins expecting fewer than `min_expected` samples are pooled into one."""
    small = expected < min_expected
    obs = np.append(counts[~small], counts[small].sum())
    exp = np.append(expected[~small], expected[small].sum())
    keep = exp > 0
    if (obs[~keep] > 0).any():  # samples where the pdf says none can land
        return 0.0
    obs, exp = obs[keep], exp[keep]
    chi2 = float(((obs - exp) ** 2 / exp).sum())
    return float(stats.chi2.sf(chi2, df=len(obs) - 1))


def sin_theta_bin_integrals(h: int) -> np.ndarray:
    """[h] exact integral of sin(pi v) dv over the sampler's rows [j/h, (j+1)/h]."""
    edges = np.arange(h + 1) / h
    return (np.cos(np.pi * edges[:-1]) - np.cos(np.pi * edges[1:])) / np.pi


# -- (a) the pdf integrates to one -----------------------------------------------------------------


def test_pdf_integrates_to_one_identity(sunrise: EnvironmentMap) -> None:
    """Midpoint rule on a (u, v) grid 4x finer than the sampler's bins, d omega = 2 pi^2 sin(theta) du dv.
    pdf * sin(theta) is constant inside each bin and the grid is aligned with the bins, so the rule is exact
    up to float32 rounding of the pdf (~1e-6 relative); 1e-4 leaves room for that and nothing else."""
    h, w = sunrise.height, sunrise.width
    total = 0.0
    for r0 in range(0, 4 * h, 256):
        uv = uv_grid(4 * w, 4 * h, r0, r0 + 256)
        pdf = sunrise.pdf(sunrise.uv_to_direction(uv.float())).double()
        total += float((pdf * torch.sin(math.pi * uv[:, 1])).sum())
    total *= 2 * math.pi**2 / (16 * w * h)
    assert abs(total - 1.0) < 1e-4, total


def test_pdf_integrates_to_one_rotated(
    sunrise_rotated: EnvironmentMap, courtyard_rotated: EnvironmentMap
) -> None:
    """Two checks of a map with an oblique 40-degree to_world.

    1. Sunrise, on the map-frame (u, v) grid: world directions uv_to_direction(uv) are fed to pdf(), so the
       rotation and its inverse must round-trip; the rule is exact as above (tolerance 1e-4).
    2. Courtyard, on an equal-area *world* grid (2048 x 1024 points in (phi, cos theta)) that does not align
       with the rotated bins: the error is the pdf mass of bins cut by grid cells, measured at < 1e-4 for this
       map at this resolution (it halves with each doubling); 1e-3 is the quadrature tolerance. A pdf that
       forgot the sin(theta) Jacobian integrates to ~1.2 here.
    """
    env = sunrise_rotated
    h, w = env.height, env.width
    total = 0.0
    for r0 in range(0, 2 * h, 256):
        uv = uv_grid(2 * w, 2 * h, r0, r0 + 256)
        pdf = env.pdf(env.uv_to_direction(uv.float())).double()
        total += float((pdf * torch.sin(math.pi * uv[:, 1])).sum())
    total *= 2 * math.pi**2 / (4 * w * h)
    assert abs(total - 1.0) < 1e-4, total

    env = courtyard_rotated
    nphi, nz = 2048, 1024
    total = wrong = 0.0
    for z0 in range(0, nz, 256):
        d = equal_area_directions(nphi, nz, z0, z0 + 256).float()
        pdf = env.pdf(d).double()
        total += float(pdf.sum())
        sin_map = torch.sin(math.pi * env.direction_to_uv(d)[:, 1].double())
        wrong += float((pdf * sin_map).sum())  # the pdf without the 1 / sin(theta) Jacobian
    total *= 4 * math.pi / (nphi * nz)
    wrong *= 4 * math.pi / (nphi * nz)
    assert abs(total - 1.0) < 1e-3, total
    assert abs(wrong - 1.0) > 1e-2, wrong


# -- (b) sampled directions follow the pdf ---------------------------------------------------------


def test_samples_follow_pdf_map_frame(sunrise: EnvironmentMap) -> None:
    """Chi-square over 16 x 8 (u, v) bins of the map frame, N = 200k samples, fixed seed.

    The coarse bins are unions of whole sampler bins, so the exact expected probability of a coarse bin is the
    sum of bin_prob over it (the integral of pdf * 2 pi^2 sin(theta) over a sampler bin is bin_prob), and the
    statistic is Pearson's chi-square (127 degrees of freedom, fewer after pooling bins expecting < 5).
    Wrong variant: a distribution whose bins forgot the sin(theta) solid-angle factor (luminance only,
    bin_prob / sin(centre), renormalised); the same statistic must reject it. (The Jacobian-free *pdf*
    cannot be told apart here: inside one of 512 rows sin(theta) is almost constant; the world-frame test
    below rejects that one.)
    """
    env = sunrise
    h, w = env.height, env.width
    gen = torch.Generator().manual_seed(1)
    d, _, _ = env.sample(torch.rand(N_SAMPLES, 2, generator=gen))
    uv = env.direction_to_uv(d).double()
    cu, cv = 16, 8
    col = (uv[:, 0] * cu).long().clamp(0, cu - 1)
    row = (uv[:, 1] * cv).long().clamp(0, cv - 1)
    counts = torch.bincount(row * cu + col, minlength=cu * cv).numpy()

    prob = env.bin_prob.double().numpy()
    expected = prob.reshape(cv, h // cv, cu, w // cu).sum(axis=(1, 3)).reshape(-1) * N_SAMPLES
    p_ok = chi_square_p(counts, expected)

    sin_centre = np.sin(np.pi * (np.arange(h) + 0.5) / h)
    wrong = prob / sin_centre[:, None]
    wrong /= wrong.sum()
    expected_wrong = wrong.reshape(cv, h // cv, cu, w // cu).sum(axis=(1, 3)).reshape(-1) * N_SAMPLES
    p_wrong = chi_square_p(counts, expected_wrong)
    assert p_ok > P_MIN, p_ok
    assert p_wrong < 1e-6, p_wrong


def test_samples_follow_pdf_world_frame(courtyard_rotated: EnvironmentMap) -> None:
    """Chi-square over 16 x 8 equal-area *world* bins (phi, cos theta) for the rotated map, N = 200k.

    Expected probabilities come from the midpoint rule of the pdf on a 1024 x 512 equal-area world grid
    (each point 4 pi / (1024 * 512) sr; 64 x 64 points per chi-square bin, aligned with the bins). Its error
    is < 1e-4 of the total (see the rotated integration test), i.e. < 20 of 200k samples spread over 128 bins
    of ~1,500 expected each, below the Poisson noise sqrt(1500) ~ 40 of every bin. This checks sample() and
    pdf() agree on to_world. The Jacobian-free pdf must be rejected.
    """
    env = courtyard_rotated
    cphi, cz = 16, 8
    nphi, nz = 1024, 512
    d = equal_area_directions(nphi, nz).float()
    pdf = env.pdf(d).double()
    sin_map = torch.sin(math.pi * env.direction_to_uv(d)[:, 1].double())
    b = world_bin(d, cphi, cz)
    expected = torch.bincount(b, weights=pdf, minlength=cphi * cz).numpy()
    expected_wrong = torch.bincount(b, weights=pdf * sin_map, minlength=cphi * cz).numpy()
    expected *= N_SAMPLES / expected.sum()
    expected_wrong *= N_SAMPLES / expected_wrong.sum()

    gen = torch.Generator().manual_seed(2)
    samples, _, _ = env.sample(torch.rand(N_SAMPLES, 2, generator=gen))
    counts = torch.bincount(world_bin(samples, cphi, cz), minlength=cphi * cz).numpy()
    p_ok = chi_square_p(counts, expected)
    p_wrong = chi_square_p(counts, expected_wrong)
    assert p_ok > P_MIN, p_ok
    assert p_wrong < 1e-6, p_wrong


# -- (c) what sample() returns agrees with pdf() and eval() ----------------------------------------


@pytest.mark.parametrize("which", ["sunrise", "sunrise_rotated"])
def test_sample_returns_pdf_and_radiance(which: str, request: pytest.FixtureRequest) -> None:
    """The pdf and radiance returned with each sample equal pdf(dirs) and eval(dirs).

    Exact equality is not expected: dirs -> (u, v) is recomputed in float32, and a sample within ~1e-7 of a
    bin edge can land in the neighbouring bin (a different pdf value). Such samples are a fraction ~1e-5;
    we allow 0.1%. Radiance is continuous (bilinear) but steep at the sun's edge (35,000 next to ~600), so
    it must match within what moving (u, v) by the float32 round-trip error allows: 1e-4 relative, or the
    largest change of the lookup when u or v moves by 1e-5 (about 10 ulps of u; the acos round trip is
    worst near the poles), for every sample.
    """
    env: EnvironmentMap = request.getfixturevalue(which)
    gen = torch.Generator().manual_seed(3)
    d, pdf, radiance = env.sample(torch.rand(N_SAMPLES, 2, generator=gen))
    assert torch.allclose(d.norm(dim=-1), torch.ones(N_SAMPLES), atol=1e-5)
    assert (pdf > 0).all()
    same_pdf = torch.isclose(pdf, env.pdf(d), rtol=1e-4, atol=0.0)
    assert same_pdf.float().mean() > 0.999, same_pdf.float().mean()
    looked_up = env.eval(d)
    uv = env.direction_to_uv(d)
    bound = 1e-4 * looked_up.abs() + 1e-6
    for du, dv in ((1e-5, 0.0), (-1e-5, 0.0), (0.0, 1e-5), (0.0, -1e-5)):
        moved = env.lookup_uv(uv + torch.tensor([du, dv]))
        bound = torch.maximum(bound, (moved - looked_up).abs())
    same_radiance = ((radiance - looked_up).abs() <= bound).all(dim=-1)
    assert bool(same_radiance.all()), int((~same_radiance).sum())


# -- (d) the estimator of the total power is unbiased ----------------------------------------------


def exact_luminance_integral(env: EnvironmentMap) -> float:
    """Closed form of the integral of luminance(eval(w)) over the sphere (identity to_world).

    The lookup is bilinear: integrated over u (wrapping), each column's hat integrates to 1/W, leaving the
    row mean m_j; in v it is linear between rows at v_j = j / (H - 1). With d omega = 2 pi^2 sin(pi v) du dv:
    integral = 2 pi^2 sum_j integral_{v_j}^{v_j+1} sin(pi v) [m_j (v_j+1 - v) + m_j+1 (v - v_j)] / dv dv.
    """
    lum = (env.texels.double() @ torch.tensor(LUMINANCE, dtype=torch.float64)).mean(dim=1).numpy()
    h = env.height
    a = np.arange(h - 1) / (h - 1)
    b = np.arange(1, h) / (h - 1)
    dv = 1.0 / (h - 1)

    def int_sin(x: np.ndarray) -> np.ndarray:  # antiderivative of sin(pi v)
        return -np.cos(np.pi * x) / np.pi

    def int_v_sin(x: np.ndarray) -> np.ndarray:  # antiderivative of v sin(pi v)
        return -x * np.cos(np.pi * x) / np.pi + np.sin(np.pi * x) / np.pi**2

    s0 = int_sin(b) - int_sin(a)
    s1 = int_v_sin(b) - int_v_sin(a)
    lower = (b * s0 - s1) / dv  # weight of row j
    upper = (s1 - a * s0) / dv  # weight of row j + 1
    return float(2 * math.pi**2 * (lum[:-1] * lower + lum[1:] * upper).sum())


def test_power_estimator_unbiased(sunrise: EnvironmentMap) -> None:
    """E[lum(L) / pdf] over N = 200k samples equals the exact integral within 4 standard errors
    (SE = sample std / sqrt(N); a correct estimator fails with probability 6e-5). The same estimate with the
    Jacobian-free pdf must be off by more than 4 SE."""
    env = sunrise
    exact = exact_luminance_integral(env)
    gen = torch.Generator().manual_seed(4)
    d, pdf, radiance = env.sample(torch.rand(N_SAMPLES, 2, generator=gen))
    lum = (radiance.double() @ torch.tensor(LUMINANCE, dtype=torch.float64))
    x = lum / pdf.double()
    mean, se = float(x.mean()), float(x.std()) / math.sqrt(N_SAMPLES)
    assert se > 0
    assert abs(mean - exact) < 4 * se, (mean, exact, se)

    sin_theta = torch.sin(math.pi * env.direction_to_uv(d)[:, 1].double())
    x_wrong = lum / (pdf.double() * sin_theta)
    mean_w, se_w = float(x_wrong.mean()), float(x_wrong.std()) / math.sqrt(N_SAMPLES)
    assert abs(mean_w - exact) > 4 * se_w, (mean_w, exact, se_w)


# -- (e) Mitsuba's mapping, by hand ----------------------------------------------------------------


def tiny_map() -> EnvironmentMap:
    """A 4 x 8 map, texel (j, i) = (10 j + i, 100 + i, 7): different along both axes, rows 0 and 3
    distinguishable, channel 2 constant."""
    h, w = 4, 8
    jj, ii = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    texels = np.stack([10.0 * jj + ii, 100.0 + ii, np.full((h, w), 7.0)], axis=-1).astype(np.float32)
    return EnvironmentMap(texels)


def test_mitsuba_direction_mapping() -> None:
    env = tiny_map()
    dirs = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0],
                         [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
    uv = env.direction_to_uv(dirs)
    assert uv[0, 1] == pytest.approx(0.0, abs=1e-6)  # +Y is the top row (v = 0)
    assert uv[1, 1] == pytest.approx(1.0, abs=1e-6)  # -Y is the bottom row
    # u = atan2(x, -z) / 2 pi: -Z is u = 0 (the map's left edge), +X a quarter, +Z the middle,
    # -X three quarters.
    assert uv[2:, 0].tolist() == pytest.approx([0.0, 0.25, 0.5, 0.75], abs=1e-6)
    assert uv[2:, 1].tolist() == pytest.approx([0.5] * 4, abs=1e-6)
    # Round trips, identity and rotated.
    gen = torch.Generator().manual_seed(5)
    d = torch.nn.functional.normalize(torch.randn(1000, 3, generator=gen), dim=-1)
    for rot in (None, OBLIQUE):
        e = EnvironmentMap(np.ones((4, 8, 3), np.float32), rot)
        assert torch.allclose(e.uv_to_direction(e.direction_to_uv(d)), d, atol=1e-5)
        uv = torch.rand(1000, 2, generator=gen) * 0.98 + 0.01
        assert torch.allclose(e.direction_to_uv(e.uv_to_direction(uv)), uv, atol=1e-5)
    # to_world takes map-frame directions to the world: the map's -Z (u = 0, v = 0.5) is seen at
    # R @ (0, 0, -1).
    e = EnvironmentMap(np.ones((4, 8, 3), np.float32), OBLIQUE)
    world = torch.as_tensor(OBLIQUE @ np.array([0.0, 0.0, -1.0]), dtype=torch.float32)[None]
    assert e.direction_to_uv(world)[0].tolist() == pytest.approx([0.0, 0.5], abs=1e-5)


def test_bilinear_texel_placement() -> None:
    """Rows at v = j / (H - 1), columns at u = (i + 0.5) / W, bilinear, wrapping in u (values by hand)."""
    env = tiny_map()
    cases = [
        # (u, v) -> expected RGB
        ((0.5 / 8, 0.0), (0.0, 100.0, 7.0)),  # texel (0, 0) centre
        ((3.5 / 8, 1.0 / 3), (13.0, 103.0, 7.0)),  # texel (1, 3): rows at j / (H - 1), not (j + 0.5) / H
        ((7.5 / 8, 1.0), (37.0, 107.0, 7.0)),  # texel (3, 7), bottom row at v = 1
        ((1.0 / 8, 0.0), (0.5, 100.5, 7.0)),  # halfway between columns 0 and 1
        ((0.0, 0.0), (3.5, 103.5, 7.0)),  # u = 0 wraps: halfway between columns 7 and 0
        ((0.99 / 8 + 0.5 / 8, 0.5), (15.99, 100.99, 7.0)),  # v = 0.5 is halfway between rows 1 and 2
        ((2.5 / 8, 1.0 / 6), (7.0, 102.0, 7.0)),  # halfway between rows 0 and 1
    ]
    uv = torch.tensor([c[0] for c in cases], dtype=torch.float32)
    got = env.lookup_uv(uv)
    want = torch.tensor([c[1] for c in cases], dtype=torch.float32)
    assert torch.allclose(got, want, atol=1e-4), (got, want)
    # The same through directions: +Y (v = 0) reads row 0 only, -Y row 3 only.
    top = env.eval(torch.tensor([[0.0, 1.0, 0.0]]))[0]
    bottom = env.eval(torch.tensor([[0.0, -1.0, 0.0]]))[0]
    assert 0.0 <= float(top[0]) <= 7.0 and float(top[1]) >= 100.0
    assert 30.0 <= float(bottom[0]) <= 37.0
    assert float(bottom[0]) - float(top[0]) == pytest.approx(30.0, abs=1e-4)
    # The direction towards texel (1, 3)'s centre reads that texel exactly.
    d = env.uv_to_direction(torch.tensor([[3.5 / 8, 1.0 / 3]]))
    assert torch.allclose(env.eval(d)[0], torch.tensor([13.0, 103.0, 7.0]), atol=1e-3)


def test_constant_map_pdf() -> None:
    """A constant map: bins weighted by sin(theta) at their centres c_j, so by hand
    pdf = sin(c_j) / sum_k sin(c_k) * H / (2 pi^2 sin(theta)), within 1% of 1 / (4 pi) at the equator
    (sin(c_j) = cos(pi / 32) there, and sum_k sin(c_k) = 1 / sin(pi / 32) ~ 2 H / pi)."""
    h = 16
    env = EnvironmentMap.constant((2.0, 2.0, 2.0), height=h)
    gen = torch.Generator().manual_seed(6)
    d, pdf, radiance = env.sample(torch.rand(10_000, 2, generator=gen))
    v = env.direction_to_uv(d)[:, 1].double()
    centre = torch.sin(math.pi * ((v * h).floor() + 0.5) / h)
    norm = sum(math.sin(math.pi * (k + 0.5) / h) for k in range(h))
    want = centre / norm * h / (2 * math.pi**2 * torch.sin(math.pi * v))
    # Samples within ~3e-4 rad of a pole round-trip to v = 0 (float32 acos): allow 0.1% of them to differ.
    same = torch.isclose(pdf.double(), want, rtol=1e-3)
    assert same.double().mean() > 0.999, same.double().mean()
    equator = env.pdf(torch.tensor([[1.0, 0.0, 0.0]]))
    assert float(equator) == pytest.approx(1 / (4 * math.pi), rel=1e-2)
    assert torch.allclose(radiance, torch.full_like(radiance, 2.0))
