"""How far the neural TTO's start (init="pbr") is from the PBR solution it starts from, in clean PathTrace PSNR.

    NEUMATEX_SHARED=../shared .venv/bin/python bench/pbr_start.py [--objects test-000000,test-000001]
        [--fit-steps 300,1500] [--bsdf-steps 0,300] [--basis ID] [--threads 2]

Per benchmark object with references (`neumatex references`): the PBR baseline's TTO (`pbr_steps` steps of the cpu
preset from the LMRM's PBR head, as tto/pbr_start.py runs it) is the reference, scored clean on orbital views 0, 4,
8, 12, 16 (eval/references.py); then the same solution expressed in the neural basis per point
(materials/pbr_to_neural.py: the basis's share of the loss) and the neural triplane fitted to it through the frozen
material decoder at each --fit-steps (tto/pbr_start.py `fit_planes`: the triplane's share), each then refined in
BSDF space for each --bsdf-steps (`refine_to_pbr_bsdf`: what the encoder's conversion loses). Prints each as dB
against the PBR solution and appends a JSON line to bench/results/pbr_start.jsonl. Needs the LMRM prediction of
each object: it runs the pipeline's validate / prepare_views / lmrm stages into --work (resumable).
"""

from __future__ import annotations

import copy
import sys
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import argument_parser, prepared_capture, write_result  # noqa: E402

from neumatex_core.eval.references import clean_metrics, harness_envmap  # noqa: E402
from neumatex_core.fields.triplane import Triplane  # noqa: E402
from neumatex_core.geometry.surface import SurfaceInteraction  # noqa: E402
from neumatex_core.lmrm.inference import LMRMPrediction  # noqa: E402
from neumatex_core.materials.field import MaterialField  # noqa: E402
from neumatex_core.materials.neural_basis import NeuralBasis, NeuralMaterial, load_basis  # noqa: E402
from neumatex_core.materials.pbr_to_neural import pbr_to_neural  # noqa: E402
from neumatex_core.tto.config import TTOConfig  # noqa: E402
from neumatex_core.tto.optimise import build_problem, decoder_for, optimise  # noqa: E402
from neumatex_core.tto.params import NeuralTriplane, PBRTriplane  # noqa: E402
from neumatex_core.tto.pbr_start import FIT_POINTS, fit_planes, refine_to_pbr_bsdf  # noqa: E402

VIEWS = (0, 4, 8, 12, 16)
SPP_HALF = 32


class PerPointConversion(MaterialField):
    """The PBR field expressed in the basis at every shaded point (no triplane in between)."""

    def __init__(self, pbr: PBRTriplane, basis: NeuralBasis) -> None:
        self.pbr, self.basis = pbr, basis

    def at(self, si: SurfaceInteraction) -> NeuralMaterial:
        v = self.pbr.gbuffer(si.position, None)
        rho, latent = pbr_to_neural(self.basis, v[:, :3], v[:, 3], v[:, 4])
        return NeuralMaterial(self.basis, rho, latent)


def start_triplane(pred: LMRMPrediction, basis: NeuralBasis) -> NeuralTriplane:
    """A trainable copy of the LMRM's planes read through a copy of its material decoder, resized where `basis` has
    another latent size (`decoder_for`, as the extraction's start does): what `fit_planes` fits to the PBR
    solution."""
    planes = pred.triplane.planes.detach().clone().requires_grad_(True)
    return NeuralTriplane(Triplane.from_planes(planes), copy.deepcopy(decoder_for(pred.material_decoder, basis)), basis)


def bench_object(object_dir: Path, work: Path, fit_steps: list[int], bsdf_steps: list[int],
                 basis: NeuralBasis) -> dict[str, Any]:
    _, pred, cap, mesh, photos = prepared_capture(object_dir, work)
    scene_mesh = mesh if mesh.vertex_normals is not None else mesh.with_smooth_normals()
    tto = TTOConfig.preset("cpu")
    cfg = TTOConfig.preset("cpu", material="pbr", init="lmrm", reg="none", steps=tto.pbr_steps)

    def score(field: MaterialField) -> float:
        with torch.no_grad():
            return float(clean_metrics(object_dir, field, scene_mesh, VIEWS, [], SPP_HALF, 0)["psnr_pathtrace_clean"])

    t0 = time.perf_counter()
    problem = build_problem(cfg, mesh, harness_envmap(cap), photos, cap.tonemap, pred, basis, True)
    pbr = optimise(problem, cfg, None, None, None).params
    assert isinstance(pbr, PBRTriplane)
    out: dict[str, Any] = {"object": object_dir.name, "pbr_steps": cfg.steps,
                           "pbr_tto_s": round(time.perf_counter() - t0, 1), "pbr_db": score(pbr.field())}  # fmt: skip
    out["per_point_db"] = score(PerPointConversion(pbr, basis))
    points, _ = scene_mesh.sample_surface(FIT_POINTS, seed=0)
    with torch.no_grad():
        v = pbr.gbuffer(points, None)
        rho, latent = pbr_to_neural(basis, v[:, :3], v[:, 3], v[:, 4])
    out["fits"] = []
    for steps in fit_steps:
        for refine in bsdf_steps:
            neural = start_triplane(pred, basis)
            t0 = time.perf_counter()
            mse = fit_planes(neural, points, rho, latent, 0, steps)
            bsdf_loss = refine_to_pbr_bsdf(neural, basis, points, v, 0, refine) if refine else None
            out["fits"].append({"steps": steps, "bsdf_steps": refine, "mse": mse, "bsdf_loss": bsdf_loss,
                                "seconds": round(time.perf_counter() - t0, 1), "db": score(neural.field())})
    return out


def main() -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--data", default="data/benchmark-test")
    parser.add_argument("--objects", default="test-000000,test-000001")
    parser.add_argument("--work", default="runs/bench-pbr-start", help="pipeline work folders (LMRM predictions)")
    parser.add_argument("--fit-steps", default="300,1500")
    parser.add_argument("--bsdf-steps", default="0,300", help="BSDF-space refinement steps after each fit")
    parser.add_argument("--basis", default="", help="an installed basis id ('': the default)")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    basis = load_basis("cpu", args.basis)
    fit_steps = [int(s) for s in args.fit_steps.split(",")]
    bsdf_steps = [int(s) for s in args.bsdf_steps.split(",")]
    rows = []
    for name in args.objects.split(","):
        row = bench_object(Path(args.data) / name, Path(args.work) / name, fit_steps, bsdf_steps, basis)
        rows.append(row)
        fits = ", ".join(f"fit {f['steps']} + BSDF {f['bsdf_steps']} steps {f['db']:.2f} dB "
                         f"({f['db'] - row['pbr_db']:+.2f}, {f['seconds']} s)" for f in row["fits"])
        print(f"{name}: PBR solution ({row['pbr_steps']} steps) {row['pbr_db']:.2f} dB clean; per point in the "
              f"basis {row['per_point_db']:.2f} ({row['per_point_db'] - row['pbr_db']:+.2f}); {fits}", flush=True)
    print(f"appended to {write_result('pbr_start', {'basis': basis.basis_id, 'views': list(VIEWS), 'rows': rows})}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
