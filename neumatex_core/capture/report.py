"""`neumatex validate CAPTURE`: print every problem of a capture in plain words, never a traceback."""

from __future__ import annotations

from pathlib import Path

from neumatex_core.capture.model import Problem
from neumatex_core.capture.validate import ValidationReport, inspect_capture


def format_report(path: str, report: ValidationReport) -> str:
    """The text `run_validate` prints: an OK line, or "N problems in PATH:" and one line per problem."""
    notes = [f"warning: {w}" for w in report.warnings]
    if report.ok:
        mesh = f"{report.mesh_faces} faces" if report.mesh_faces is not None else "unknown faces"
        env = f"{report.envmap_size[0]}x{report.envmap_size[1]}" if report.envmap_size else "unknown size"
        return "\n".join([f"OK: {report.n_frames} frames, mesh {mesh}, envmap {env}", *notes])
    lines = [f"{len(report.problems)} problems in {path}:"]
    lines += [f"  {p}" for p in report.problems]
    return "\n".join(lines + notes)


def run_validate(path: str, allow_outside: bool = False) -> int:
    """Validate the capture folder or zip at `path`, print the result; 0 when valid, 1 otherwise. `allow_outside`:
    a folder's transforms.json may name files outside it (local use; `allow_outside_paths`)."""
    from neumatex_core.capture.loader import allow_outside_paths

    try:
        with allow_outside_paths(allow_outside):
            report = inspect_capture(path)
    except Exception as exc:  # bad input must never end in a traceback: report it as a problem
        name = Path(path).name or path
        report = ValidationReport(
            problems=[Problem(name, f"could not be validated ({type(exc).__name__}: {exc})")]
        )
    print(format_report(path, report), flush=True)
    return 0 if report.ok else 1
