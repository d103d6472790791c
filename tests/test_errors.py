"""Results are written whole or not at all, and never overwritten without --force."""

import os

import pytest

from jaxcos import InputError
from jaxcos._errors import staged_outputs


def _write(folder, names):
    for name in names:
        with open(os.path.join(folder, name), "w", encoding="utf-8") as fh:
            fh.write(name)


def test_staged_outputs_moves_every_file_in_at_the_end(tmp_path):
    out = tmp_path / "result"
    with staged_outputs(out, ("a.txt", "b.txt"), force=False) as tmp:
        _write(tmp, ("a.txt", "b.txt"))
        assert not (out / "a.txt").exists()
    assert sorted(os.listdir(out)) == ["a.txt", "b.txt"]


def test_staged_outputs_leaves_nothing_behind_on_an_error(tmp_path):
    out = tmp_path / "result"
    with pytest.raises(RuntimeError):
        with staged_outputs(out, ("a.txt", "b.txt"), force=False) as tmp:
            _write(tmp, ("a.txt",))
            raise RuntimeError("a figure failed")
    assert not out.exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "other.txt").write_text("mine")
    with pytest.raises(RuntimeError):
        with staged_outputs(kept, ("a.txt",), force=False) as tmp:
            raise RuntimeError("a figure failed")
    assert os.listdir(kept) == ["other.txt"]


def test_staged_outputs_refuses_to_overwrite_without_force(tmp_path):
    (tmp_path / "a.txt").write_text("old")
    with pytest.raises(InputError, match="already exists"):
        with staged_outputs(tmp_path, ("a.txt",), force=False) as tmp:
            _write(tmp, ("a.txt",))
    assert (tmp_path / "a.txt").read_text() == "old"
    with staged_outputs(tmp_path, ("a.txt",), force=True) as tmp:
        _write(tmp, ("a.txt",))
    assert (tmp_path / "a.txt").read_text() == "a.txt"
