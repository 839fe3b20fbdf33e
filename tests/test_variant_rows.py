"""How bench/variants_clean.py makes a variant's results from stored rows for the default's page: a variant with a
second basis on held-out photos (TTOConfig.select_basis) from its two sides' results, and a side without the
alternative basis from the rows of a variant that differs in the alternative alone wherever that one's start stayed
in the configured basis (docs/design-notes.md items 80, 81)."""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent.parent / "bench"
M0 = "pbr_start_default_settle_decdb_slr10_s900_m0"


def variants_clean() -> Any:
    sys.path.insert(0, str(BENCH))
    try:
        return importlib.import_module("variants_clean")
    finally:
        sys.path.remove(str(BENCH))


def result(pathtrace: float, uniform: float, textured: float, switched: float | None = None) -> dict[str, Any]:
    """A stored result: its PathTrace score and its uniform/textured choice's held-out scores (uniform kept unless
    textured scores higher), and where the variant has an alternative basis whether its start switched to it."""
    row: dict[str, Any] = {"psnr_pathtrace_clean": pathtrace, "choice_validation_photos": 4.0,
                           "choice_validation_psnr_uniform": uniform, "choice_validation_psnr_textured": textured,
                           "choice_uniform_kept": float(textured <= uniform)}  # fmt: skip
    if switched is not None:
        row["choice_basis_switched"] = switched
    return row


def test_the_default_without_v4_reads_v1s_side_from_rows_whose_start_stayed_in_v1(tmp_path, monkeypatch):
    vc = variants_clean()
    monkeypatch.setattr(vc, "own_rows", lambda: [])  # the page's results alone, not bench/results' rows
    assert vc.basis_sides("default_choose_v6_alone") == ("default_v1", "default_v6_dec")
    assert M0 in vc.start_stand_ins("default_v1")
    assert "default_v6_dec" not in vc.start_stand_ins("default_v1")  # another basis, not the alternative alone
    assert vc.start_stand_ins(M0) == []  # it has the alternative itself

    def write(obj: str, variant: str, row: dict[str, Any]) -> None:
        path = tmp_path / "results" / obj / f"{variant}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(row))

    write("kept", M0, result(30.0, 25.0, 24.0, switched=0.0))  # v1 held the start: M0's result is default_v1's
    write("kept", "default_v6_dec", result(31.0, 24.5, 24.8))  # v6's kept candidate 24.8 < v1's 25.0
    write("taken", M0, result(30.0, 25.0, 24.0, switched=0.0))
    write("taken", "default_v6_dec", result(33.0, 24.0, 25.5))  # textured 25.5 > 25.0: v6 taken
    write("switched", M0, result(30.0, 25.0, 24.0, switched=1.0))  # its start in v4: not default_v1's
    write("switched", "default_v6_dec", result(33.0, 26.0, 24.0))
    write("own", M0, result(30.0, 25.0, 24.0, switched=1.0))
    write("own", "default_v1", result(28.0, 23.0, 22.0))  # default_v1 run there itself
    write("own", "default_v6_dec", result(33.0, 22.5, 22.9))  # v6's 22.9 < v1's 23.0: v1 kept
    found = vc.side_results(("default_v1", "default_v6_dec"), tmp_path)
    assert sorted(found) == ["kept", "own", "taken"]
    assert found["kept"][0][1].startswith(f"{M0}'s, its start in the configured basis")
    assert found["own"][0][0]["psnr_pathtrace_clean"] == 28.0
    made = vc.composed_rows("default_choose_v6_alone", tmp_path, have={"taken"})
    assert sorted(made) == ["kept", "own"]
    assert made["kept"]["psnr_pathtrace_clean"] == 30.0 and made["kept"]["choice_select_basis_taken"] == 0.0
    assert made["own"]["psnr_pathtrace_clean"] == 28.0 and made["own"]["choice_select_basis_taken"] == 0.0
    assert vc.composed_rows("default_choose_v6_alone", tmp_path, set())["taken"]["psnr_pathtrace_clean"] == 33.0
