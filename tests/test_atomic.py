"""neumatex_core/atomic.py: a target is the old file or the whole new one, never half; failures leave nothing."""

from __future__ import annotations

import json

import pytest

from neumatex_core.atomic import is_temporary, replaced_atomically, write_json_atomic


def test_replaced_atomically_renames_on_success_and_cleans_up_on_failure(tmp_path):
    target = tmp_path / "image.exr"
    target.write_text("old")
    with replaced_atomically(target) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".exr" and is_temporary(tmp.name)
        tmp.write_text("new")
        assert target.read_text() == "old"  # nothing visible before the body ends
    assert target.read_text() == "new"
    with pytest.raises(RuntimeError), replaced_atomically(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("writer failed")
    assert target.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["image.exr"]


def test_write_json_atomic_is_sorted_indented_and_ends_with_a_newline(tmp_path):
    write_json_atomic(tmp_path / "meta.json", {"b": 1, "a": [1, 2]})
    text = (tmp_path / "meta.json").read_text()
    assert text == '{\n "a": [\n  1,\n  2\n ],\n "b": 1\n}\n' and json.loads(text) == {"a": [1, 2], "b": 1}
    assert not is_temporary("meta.json") and is_temporary("done.json.tmp")
