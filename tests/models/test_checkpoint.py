"""Checkpoint files: atomic round trip and one clear error naming the file."""

import pytest
import torch

from models.checkpoint import FORMAT_VERSION, CheckpointError, load_checkpoint, save_checkpoint


def test_round_trip_is_atomic(tmp_path):
    path = tmp_path / "run" / "checkpoint.pt"
    payload = {"weights": {"w": torch.arange(6.0)}, "step": 3, "name": "hydo"}
    save_checkpoint(path, payload)
    save_checkpoint(path, {**payload, "step": 4})  # overwrite in place
    out = load_checkpoint(path)
    assert out["step"] == 4 and torch.equal(out["weights"]["w"], torch.arange(6.0))
    assert [p.name for p in path.parent.iterdir()] == ["checkpoint.pt"]  # no temp file left behind


def test_missing_file(tmp_path):
    with pytest.raises(CheckpointError, match="nope.pt: no such file") as e:
        load_checkpoint(tmp_path / "nope.pt")
    assert "\n" not in str(e.value)


def test_truncated_file(tmp_path):
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, {"w": torch.randn(1000)})
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="ckpt.pt: truncated or corrupt") as e:
        load_checkpoint(path)
    assert "\n" not in str(e.value)


def test_garbage_file(tmp_path):
    path = tmp_path / "junk.pt"
    path.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match="junk.pt: truncated or corrupt"):
        load_checkpoint(path)


def test_version_mismatch(tmp_path):
    path = tmp_path / "old.pt"
    torch.save({"format_version": FORMAT_VERSION + 1, "payload": {}}, path)
    with pytest.raises(
        CheckpointError, match=f"old.pt: format version {FORMAT_VERSION + 1}, this hydo reads"
    ):
        load_checkpoint(path)
    torch.save({"something": 1}, path)
    with pytest.raises(CheckpointError, match="not a hydo checkpoint"):
        load_checkpoint(path)


def test_refuses_pickled_code(tmp_path):
    path = tmp_path / "evil.pt"
    torch.save({"format_version": FORMAT_VERSION, "payload": {"obj": object()}}, path)
    with pytest.raises(CheckpointError, match="evil.pt"):
        load_checkpoint(path)  # weights_only=True: arbitrary objects are not unpickled
