"""Point encoder: shapes, invariances, input checks."""

import pytest
import torch
from learner_util import random_obs

from models.encoder import PointEncoder


def test_shapes_and_object_only_output():
    enc = PointEncoder(16, 8, out_dim=24, hidden=32, global_dim=32)
    points, features = random_obs(3, 16, 8)
    assert enc(points, features).shape == (3, 16, 24)


def test_translation_invariant_and_permutation_equivariant():
    torch.manual_seed(0)
    enc = PointEncoder(16, 8, hidden=32, global_dim=32)
    points, features = random_obs(2, 16, 8)
    out = enc(points, features)
    shifted = enc(points + torch.tensor([0.3, -0.1, 0.02]), features)  # same scene elsewhere in the bin
    assert torch.allclose(out, shifted, atol=1e-4)
    perm = torch.randperm(16)
    order = torch.cat([perm, torch.arange(16, 24)])
    assert torch.allclose(enc(points[:, order], features[:, order]), out[:, perm], atol=1e-5)


def test_bad_shapes_raise():
    enc = PointEncoder(16, 8)
    points, features = random_obs(2, 16, 8)
    with pytest.raises(ValueError, match=r"`points` must have shape \(\*, 24, 3\)"):
        enc(points[:, :20], features[:, :20])
    with pytest.raises(ValueError, match="`features` must have shape"):
        enc(points, features[..., :3])


def test_normals_input_variant():
    """With ``normals=True`` the object points' normals change the features (and get gradient);
    without them the encoder refuses; a plain encoder ignores them."""
    torch.manual_seed(0)
    enc = PointEncoder(16, 8, hidden=32, global_dim=32, normals=True)
    points, features = random_obs(2, 16, 8)
    normals = torch.nn.functional.normalize(torch.randn(2, 16, 3), dim=-1)
    out = enc(points, features, normals)
    assert out.shape == (2, 16, 64)
    assert not torch.allclose(out, enc(points, features, -normals), atol=1e-3)
    out.sum().backward()
    assert enc.local[0].weight.grad[:, 7:].abs().sum() > 0  # the normal columns learn
    with pytest.raises(ValueError, match="normals"):
        enc(points, features)
    with pytest.raises(ValueError, match="`normals` must have shape"):
        enc(points, features, normals[:, :8])
    plain = PointEncoder(16, 8, hidden=32, global_dim=32)
    assert torch.equal(plain(points, features), plain(points, features, normals))


@pytest.mark.parametrize("n_bg", [8, 0])
def test_encode_for_update_matches_the_dense_gradient(n_bg):
    """The update's sparse encoding (only the executed point and the max-pools' argmax rows are
    differentiated) gives the same executed-point features, the same detached per-point context and
    the same parameter gradient as differentiating every row."""
    torch.manual_seed(0)
    enc = PointEncoder(16, n_bg, hidden=32, global_dim=32, out_dim=24, normals=True)
    points, features = random_obs(5, 16, n_bg)
    normals = torch.nn.functional.normalize(torch.randn(5, 16, 3), dim=-1)
    index = torch.randint(0, 16, (5,))
    weight = torch.randn(5, 24)  # a loss that reaches every output feature

    ctx = enc.encode_context(points, features, normals)
    dense = enc.head(ctx.local[torch.arange(5), index], ctx.context)
    (dense * weight).sum().backward()
    dense_grads = [p.grad.clone() for p in enc.parameters()]
    enc.zero_grad()

    sparse, sparse_ctx = enc.encode_for_update(points, features, normals, index)
    (sparse * weight).sum().backward()
    assert torch.allclose(sparse, dense, atol=1e-6)
    assert not sparse_ctx.local.requires_grad and not sparse_ctx.context.requires_grad
    assert torch.allclose(sparse_ctx.local, ctx.local, atol=1e-6)
    assert torch.allclose(sparse_ctx.context, ctx.context, atol=1e-6)
    for p, g in zip(enc.parameters(), dense_grads, strict=True):
        assert p.grad is not None and torch.allclose(p.grad, g, atol=1e-5), p.shape
    assert any(g.abs().sum() > 0 for g in dense_grads)
