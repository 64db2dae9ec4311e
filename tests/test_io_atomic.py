"""Atomic writes: the file lands whole or not at all, with the mode an ordinary open() gives."""
from __future__ import annotations

import os
import stat

import pytest

from stircasadi.io import atomic_path, atomic_write_text


def test_new_file_gets_the_umask_mode_not_0600(tmp_path):
    old = os.umask(0o022)
    try:
        p = atomic_write_text(tmp_path / "a.json", "{}")
    finally:
        os.umask(old)
    assert stat.S_IMODE(p.stat().st_mode) == 0o644
    assert p.read_text() == "{}"


def test_replacing_keeps_the_existing_mode(tmp_path):
    p = tmp_path / "b.txt"
    p.write_text("old")
    os.chmod(p, 0o640)
    atomic_write_text(p, "new")
    assert stat.S_IMODE(p.stat().st_mode) == 0o640 and p.read_text() == "new"


def test_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    p = tmp_path / "c.txt"
    p.write_text("kept")
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_text("half")
            raise RuntimeError("writer died")
    assert p.read_text() == "kept"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["c.txt"]
