"""Make a bundled example (examples/) from a `neumatex synth` object: drop what an extraction does not read.

    python tools/prune_example.py runs/example-coat-256/test-000040 examples/coat-teapot [--keep-gbuffers K,...]

Removes the linear EXR renders (`linear/`, every frame's `linear_path`) of the object and of its photos/ capture,
and every ground-truth G-buffer except the kinds in --keep-gbuffers (default none; the extraction tests' example
keeps position,basecolor,latent), with their keys in transforms.json and their entries in meta.json's file hashes
(meta.json's tree hash goes with them: it no longer describes the folder). See examples/README.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path


def prune_transforms(path: Path, keep: set[str]) -> None:
    doc = json.loads(path.read_text())
    for frame in doc["frames"]:
        frame.pop("linear_path", None)
        gbuffers = {k: v for k, v in frame.get("gbuffers", {}).items() if k in keep}
        if gbuffers:
            frame["gbuffers"] = gbuffers
        else:
            frame.pop("gbuffers", None)
    path.write_text(json.dumps(doc, indent=1) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("object", type=Path, help="a synth object folder (runs/<out>/<split>-<index>)")
    parser.add_argument("out", type=Path, help="the example folder to write (must not exist)")
    parser.add_argument("--keep-gbuffers", default="", help="comma-separated G-buffer kinds to keep")
    args = parser.parse_args(argv)
    if args.out.exists():
        print(f"error: {args.out} exists", file=sys.stderr)
        return 2
    keep = {k for k in args.keep_gbuffers.split(",") if k}
    shutil.copytree(args.object, args.out, ignore=shutil.ignore_patterns("linear"))
    for transforms in (args.out / "transforms.json", args.out / "photos" / "transforms.json"):
        if transforms.is_file():
            prune_transforms(transforms, keep)
    for g in sorted((args.out / "gbuffers").glob("*.exr")) if (args.out / "gbuffers").is_dir() else []:
        if g.stem.split("_", 1)[1] not in keep:
            g.unlink()
    if (args.out / "gbuffers").is_dir() and not any((args.out / "gbuffers").iterdir()):
        (args.out / "gbuffers").rmdir()
    meta_path = args.out / "meta.json"
    meta = json.loads(meta_path.read_text())
    meta["files"] = {f: h for f, h in meta.get("files", {}).items() if (args.out / f).is_file()}
    meta.pop("tree_sha256", None)
    meta["note"] = (f"pruned for examples/ by tools/prune_example.py: linear renders removed; G-buffers kept: "
                    f"{', '.join(sorted(keep)) or 'none'}")
    meta_path.write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
