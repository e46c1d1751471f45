"""sim.atomic: a write that fails part-way leaves the previous file whole and no temp file behind."""

import stat

import pytest

from sim.atomic import atomic_write, atomic_write_text


def test_atomic_write_replaces_and_sets_mode(tmp_path):
    p = tmp_path / "sub" / "a.json"
    atomic_write_text(p, "one")
    atomic_write_text(p, "two")
    assert p.read_text() == "two"
    assert stat.S_IMODE(p.stat().st_mode) == 0o644
    assert sorted(x.name for x in p.parent.iterdir()) == ["a.json"]


def test_failed_write_keeps_the_old_file(tmp_path):
    p = tmp_path / "ckpt.bin"
    atomic_write_text(p, "good")

    def torn(f):
        f.write(b"half")
        raise RuntimeError("crash while writing")

    with pytest.raises(RuntimeError, match="crash while writing"):
        atomic_write(p, torn)
    assert p.read_text() == "good"
    assert [x.name for x in tmp_path.iterdir()] == ["ckpt.bin"]
