"""Minutes the pipeline's prepare_views stage spends per capture: the 23 preset views blended (unstructured
lumigraph, novel_view/lumigraph.py) from a capture's random-pose photos.

    NEUMATEX_SHARED=../shared .venv/bin/python bench/prepare_views.py [--capture examples/coat-teapot/photos]
        [--preset cpu] [--repeats 3] [--threads 2]

Times `run_stage("prepare_views", ...)` (a fresh work folder each repeat; the validate stage before it is not timed)
and, as the reference measured in the same run, loading the same capture (load_capture, every photo and mask
through the tonemap inverse, the mesh): the stage's cost in units of "reading the capture once". Prints the minutes
per capture, the seconds per photo and the ratio, and appends a JSON line to bench/results/prepare_views.jsonl.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import argument_parser, time_repeats, write_result  # noqa: E402

from neumatex_core.capture import load_capture  # noqa: E402
from neumatex_core.pipeline import ExtractConfig, run_stage  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def main() -> int:
    ap = argument_parser(__doc__)
    ap.add_argument("--capture", default=str(REPO / "examples" / "coat-teapot" / "photos"))
    ap.add_argument("--preset", default="cpu", choices=["tiny", "cpu", "gpu"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    capture = Path(args.capture)
    config = ExtractConfig.preset(args.preset, device="cpu")
    root = Path(tempfile.mkdtemp(prefix="bench-prepare-views-"))
    try:
        validated = root / "validated"
        run_stage("validate", capture, validated, config)
        runs = iter(range(10**6))

        def prepare() -> None:
            work = root / f"work{next(runs)}"
            shutil.copytree(validated, work)
            run_stage("prepare_views", capture, work, config)

        def load() -> None:
            with load_capture(capture) as cap:
                for i in range(len(cap.frames)):
                    cap.tonemap.display_to_linear(cap.load_image(i))
                    cap.load_mask(i)
                cap.load_mesh()

        with load_capture(capture) as cap:
            n_photos, size = len(cap.frames), (cap.cameras[0].width, cap.cameras[0].height)
        reference = time_repeats(load, repeats=args.repeats, warmup=1)
        stage = time_repeats(prepare, repeats=args.repeats)
        source = (root / "work0" / "prepare_views" / "views.json").read_text()
    finally:
        shutil.rmtree(root, ignore_errors=True)
    seconds, ref = stage["min"], reference["min"]
    record = {
        "config": {"capture": str(capture), "photos": n_photos, "photo_size": list(size), "preset": args.preset,
                   "view_resolution": config.view_resolution, "blend_k": config.blend_k, "threads": args.threads,
                   "repeats": args.repeats},  # fmt: skip
        "prepare_views_s": seconds, "prepare_views_minutes": seconds / 60, "seconds_per_photo": seconds / n_photos,
        "reference_load_capture_s": ref, "ratio_to_load": seconds / ref,
        "stage_times": stage["times"], "reference_times": reference["times"],
        "foreign_cpu": stage["foreign_cpu"], "blended": "blended from" in source,
    }  # fmt: skip
    path = write_result("prepare_views", record)
    print(f"prepare_views ({args.preset} preset, {config.view_resolution} px views from {n_photos} photos of "
          f"{size[0]}x{size[1]}, {args.threads} threads): {seconds:.2f} s = {seconds / 60:.3f} min per capture, "
          f"{seconds / n_photos:.2f} s per photo; loading the capture takes {ref:.3f} s, so the stage costs "
          f"{seconds / ref:.0f}x reading the capture once (other processes kept {stage['foreign_cpu']} of the CPUs "
          f"busy) -> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
