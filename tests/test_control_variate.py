"""The control variate of the TTO's photo renders (tto/control_variate.py, `TTOConfig.control_variate`): the same
expectation as a plain render with a fraction of its noise, and it acts only where it is asked for (a TTO with it
resumes bit for bit inside a round: tests/test_tto.py)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.tto import TTOConfig, build_problem, optimise
from neumatex_core.tto.control_variate import ControlVariate, clone_generator

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def test_the_control_variate_keeps_the_renders_expectation_with_much_less_noise(example, truth_prediction):
    from test_tto import perturbed  # the TTO tests' helper

    cfg = TTOConfig.preset("tiny", init="lmrm", reg="none")

    def params(std: float):
        return build_problem(cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap,
                             perturbed(truth_prediction, std), example.basis).params  # fmt: skip

    reference, moved = params(0.0), params(0.1)  # the reference theta_0 and a material that has moved from it
    mesh = example.mesh if example.mesh.vertex_normals is not None else example.mesh.with_smooth_normals()
    scene = Scene(mesh, example.envmap, moved.field())
    tracer = PathTracer(PathTracerConfig(max_bounces=2, rr_depth=2, spp=4))
    variate = ControlVariate(reference, scene, example.photos, tracer, 16, torch.Generator().manual_seed(7))
    spp, n = 4, 1024
    g = torch.Generator().manual_seed(1)
    batch = example.photos.batch(n, spp, g)
    pixel = lambda r: r.reshape(n, spp, 3).mean(1)  # noqa: E731
    plain, cv = [], []
    with torch.no_grad():
        for seed in (11, 12):  # two draws of the paths of the same rays
            g = torch.Generator().manual_seed(seed)
            twin = clone_generator(g)
            plain.append(tracer.render_rays(scene, batch.origins, batch.directions, g))
            cv.append(variate.radiance(plain[-1], batch.origins, batch.directions, batch.index, spp, twin))
        # the expectation of the moved material's render of these rays: 32 independent renders
        truth = torch.stack([tracer.render_rays(scene, batch.origins, batch.directions,
                                                torch.Generator().manual_seed(100 + k)) for k in range(32)]).mean(0)
    d_cv = (pixel(cv[0]) - pixel(truth)).mean(1)
    # the same expectation (over the reference's fixed noise too): the mean difference within 4 standard errors of 0
    assert abs(float(d_cv.mean())) < 4 * float(d_cv.std()) / math.sqrt(n), (float(d_cv.mean()), float(d_cv.std()))
    # the fresh noise, what changes from one step's draw to the next: a small fraction of a plain render's
    # (measured about 1/20 here; 1/40-1/1500 on benchmark object 0, docs/design-notes.md item 57)
    fresh_cv = float((pixel(cv[0]) - pixel(cv[1])).var())
    fresh_plain = float((pixel(plain[0]) - pixel(plain[1])).var())
    assert fresh_cv < 0.2 * fresh_plain, (fresh_cv, fresh_plain)

def test_the_control_variate_acts_where_it_is_asked_for(example, truth_prediction):
    from test_tto import perturbed

    # settling from step 4, a copy made again every 2 steps (the stop and resume inside a round: test_tto.py)
    cfg = TTOConfig.preset("tiny", steps=8, pixels=64, spp=2, max_bounces=2, checkpoint_every=0, init="lmrm",
                           settle_fraction=0.5, settle_spp=4, control_variate="settle", cv_spp=4, cv_refresh=2)

    def run(config: TTOConfig):
        return optimise(build_problem(config, example.mesh, example.envmap, example.photos, example.capture.tonemap,
                                      perturbed(truth_prediction, 0.2), example.basis), config)  # fmt: skip

    with_variate, plain = run(cfg), run(replace(cfg, control_variate="off"))
    # the same pixels and paths: the steps before the settling agree, the variate changes the others
    assert with_variate.history[:4] == plain.history[:4] and with_variate.history[4:] != plain.history[4:]
    assert [cfg.cv_round(s) for s in range(8)] == [-1, -1, -1, -1, 4, 4, 6, 6]
    assert [replace(cfg, control_variate="all", cv_refresh=3).cv_round(s) for s in range(8)] == [0, 0, 0, 3, 4, 4, 4, 7]
    with pytest.raises(ValueError, match="control_variate"):
        replace(cfg, estimator="cached", settle_fraction=0.0).check()
