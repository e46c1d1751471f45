"""Replay buffer: round trip, terminated vs truncated, memory accounting, save/load."""

import numpy as np
import pytest
import torch

from models.replay import ReplayBuffer, rotate_yaw90


def transition(rng, n_obj=4, n_bg=4, e=None):
    lead = () if e is None else (e,)
    n = n_obj + n_bg
    return dict(
        points=rng.normal(0, 0.2, lead + (n, 3)).astype(np.float32),
        features=rng.normal(0, 0.05, lead + (n, 4)).astype(np.float32),
        index=rng.integers(0, n_obj, lead) if e else int(rng.integers(0, n_obj)),
        motion=rng.uniform(-1, 1, lead + (3,)).astype(np.float32),
        reward=rng.normal(size=lead).astype(np.float32) if e else float(rng.normal()),
        next_points=rng.normal(0, 0.2, lead + (n, 3)).astype(np.float32),
        next_features=rng.normal(0, 0.05, lead + (n, 4)).astype(np.float32),
        terminated=rng.random(lead) < 0.5 if e else True,
        truncated=rng.random(lead) < 0.5 if e else False,
    )


def test_round_trip_single_and_batched():
    rng = np.random.default_rng(0)
    buf = ReplayBuffer(10, 4, 4)
    t = transition(rng)
    buf.add(**t)
    batch = buf.sample(3)
    assert batch.points.dtype == torch.float32 and batch.points.shape == (3, 8, 3)
    assert batch.index.dtype == torch.int64
    np.testing.assert_allclose(batch.points[0].numpy(), t["points"], atol=2e-4)  # float16 storage
    np.testing.assert_allclose(batch.next_features[0].numpy(), t["next_features"], atol=1e-4)
    assert batch.index[0].item() == t["index"]
    np.testing.assert_array_equal(batch.motion[0].numpy(), t["motion"])  # motions exact, in [-1, 1]
    assert batch.terminated[0].item() == 1.0 and batch.truncated[0].item() == 0.0
    buf.add(**transition(rng, e=5))
    assert len(buf) == 6


def test_terminated_and_truncated_are_kept_apart():
    rng = np.random.default_rng(1)
    buf = ReplayBuffer(64, 4, 4)
    t = transition(rng, e=64)
    buf.add(**t)
    np.testing.assert_array_equal(buf.terminated, t["terminated"])
    np.testing.assert_array_equal(buf.truncated, t["truncated"])
    assert (buf.terminated != buf.truncated).any()


def test_fifo_wraps_around():
    rng = np.random.default_rng(2)
    buf = ReplayBuffer(4, 4, 4)
    rewards = []
    for _ in range(6):
        t = transition(rng)
        rewards.append(t["reward"])
        buf.add(**t)
    assert len(buf) == 4 and buf.full
    assert sorted(buf.reward.tolist()) == pytest.approx(sorted(rewards[2:]))


def test_bytes_per_transition_and_capacity_estimate():
    buf = ReplayBuffer(1, 128, 128)
    assert buf.bytes_per_transition == 2 * 256 * 7 * 2 + 4 + 12 + 4 + 2  # two float16 clouds + action, flags
    assert 200_000 * buf.bytes_per_transition < 1.5 * 2**30  # 200k transitions at N=256: ~1.4 GB


def test_rejects_bad_input():
    rng = np.random.default_rng(3)
    buf = ReplayBuffer(4, 4, 4)
    with pytest.raises(ValueError, match="`index` must be in"):
        buf.add(**{**transition(rng), "index": 4})  # a background point
    with pytest.raises(ValueError, match="`points` must have shape"):
        buf.add(**{**transition(rng), "points": np.zeros((7, 3), np.float32)})
    with pytest.raises(ValueError, match="`motion` must lie in"):
        buf.add(**{**transition(rng), "motion": np.full(3, 1.5, np.float32)})


def test_save_load_resumes_sampling(tmp_path):
    rng = np.random.default_rng(4)
    buf = ReplayBuffer(16, 4, 4, seed=3)
    buf.add(**transition(rng, e=10))
    buf.sample(4)
    buf.save(tmp_path / "replay.npz")
    loaded = ReplayBuffer.load(tmp_path / "replay.npz")
    assert len(loaded) == 10 and loaded.pos == buf.pos
    a, b = buf.sample(6), loaded.sample(6)
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x, y)
    assert not list(tmp_path.glob(".*.tmp"))


def test_yaw90_turns_points_flows_and_motion_alike():
    rng = np.random.default_rng(1)
    buf = ReplayBuffer(4, 4, 4)
    t = transition(rng)
    t["motion"] = np.array([1.0, 0.5, -0.2], np.float32)
    buf.add(**t)
    batch = buf.sample(1)
    turned = rotate_yaw90(batch, torch.tensor([1]))  # +90° about z: (x, y, z) -> (-y, x, z)
    np.testing.assert_array_equal(turned.motion[0].numpy(), np.float32([-0.5, 1.0, -0.2]))
    for name in ("points", "next_points"):
        p, q = getattr(batch, name)[0], getattr(turned, name)[0]
        np.testing.assert_allclose(
            q.numpy(), torch.stack([-p[:, 1], p[:, 0], p[:, 2]], -1).numpy(), atol=1e-7
        )
    for name in ("features", "next_features"):
        f, g = getattr(batch, name)[0], getattr(turned, name)[0]
        np.testing.assert_array_equal(g[:, 0].numpy(), f[:, 0].numpy())  # is_object unchanged
        np.testing.assert_allclose(
            g[:, 1:].numpy(), torch.stack([-f[:, 2], f[:, 1], f[:, 3]], -1).numpy(), atol=1e-7
        )
    for name in ("index", "reward", "terminated", "truncated"):
        assert torch.equal(getattr(turned, name), getattr(batch, name))
    four = batch
    for _ in range(4):
        four = rotate_yaw90(four, torch.tensor([1]))
    np.testing.assert_allclose(four.points.numpy(), batch.points.numpy(), atol=1e-6)


def test_sampling_with_yaw90_uses_all_four_turns_and_keeps_motions_in_the_box():
    rng = np.random.default_rng(2)
    buf = ReplayBuffer(8, 4, 4, seed=0)
    t = transition(rng)
    t["motion"] = np.array([1.0, -1.0, 0.3], np.float32)
    buf.add(**t)
    seen = {tuple(m) for m in buf.sample(64, augment="yaw90").motion.double().numpy().round(3).tolist()}
    assert seen == {(1.0, -1.0, 0.3), (1.0, 1.0, 0.3), (-1.0, 1.0, 0.3), (-1.0, -1.0, 0.3)}
    with pytest.raises(ValueError, match="augment"):
        buf.sample(2, augment="flip")
