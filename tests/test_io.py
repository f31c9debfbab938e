"""The atomic writes and the one JSONL reader with its torn-line rule."""

from __future__ import annotations

import json

import pytest

from popsan_jax import io
from popsan_jax.errors import CheckpointError


def test_write_json_is_sorted_indented_and_leaves_no_tmp(tmp_path):
    path = io.write_json(tmp_path / "a.json", {"b": 1, "a": [1, 2]})
    assert path.read_text() == '{\n  "a": [\n    1,\n    2\n  ],\n  "b": 1\n}\n'
    io.write_json(path, {"c": 3})  # replaces
    assert json.loads(path.read_text()) == {"c": 3}
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]


def test_jsonl_round_trip_and_blank_lines(tmp_path):
    path = io.write_jsonl(tmp_path / "m.jsonl", [{"x": 1}, {"x": 2}])
    assert path.read_text() == '{"x": 1}\n{"x": 2}\n'
    path.write_text('{"x": 1}\n\n{"x": 2}\n')
    assert io.read_jsonl(path) == [{"x": 1}, {"x": 2}]


def test_a_torn_last_line_is_skipped(tmp_path):
    path = tmp_path / "m.jsonl"
    path.write_text('{"x": 1}\n{"x": 2}\n{"x": 3, "y')  # a writer killed mid-line
    assert io.read_jsonl(path) == [{"x": 1}, {"x": 2}]


@pytest.mark.parametrize(
    "text, line",
    [('{"x": 1}\n{not json}\n{"x": 3}\n', 2), ('{"x": 1}\n{"x": 2, "y\n', 2)],
)
def test_any_other_bad_line_is_damage(tmp_path, text, line):
    """A bad line followed by a newline was written whole: not a torn write."""
    path = tmp_path / "m.jsonl"
    path.write_text(text)
    with pytest.raises(CheckpointError, match=rf"m.jsonl:{line} is not valid JSON"):
        io.read_jsonl(path)


def test_bytes_that_are_not_utf8_are_one_line(tmp_path):
    path = tmp_path / "m.jsonl"
    path.write_bytes(bytes(range(128, 256)))
    with pytest.raises(CheckpointError, match="cannot read"):
        io.read_jsonl(path)


def test_writability_checks(tmp_path):
    from popsan_jax.errors import UserError
    from popsan_jax.io import check_output_file, check_writable

    check_writable(tmp_path / "not" / "yet")  # judged by its nearest existing parent
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(UserError, match="is a file, not a directory"):
        check_writable(afile / "sub")
    with pytest.raises(UserError, match="kernel filesystem"):
        check_writable("/proc/self")
    with pytest.raises(UserError, match="is a directory, not a file"):
        check_output_file(tmp_path, "--out")
    assert check_output_file(tmp_path / "new" / "f.png", "--out") == tmp_path / "new" / "f.png"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]  # nothing left behind
