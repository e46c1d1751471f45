"""Point encoder: shapes, invariances, input checks."""

import pytest
import torch
from learner_util import random_obs

from models.encoder import PointEncoder, neighbourhood_normal


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


def _square_patch(n_side: int = 5, spacing: float = 0.01) -> torch.Tensor:
    """(1, n_side², 3) a flat square grid of points at z = 0.05 m, 1 cm apart."""
    ij = torch.stack(torch.meshgrid(torch.arange(n_side), torch.arange(n_side), indexing="ij"), -1)
    xy = spacing * ij.reshape(-1, 2).float()
    return torch.cat([xy, torch.full((len(xy), 1), 0.05)], -1)[None]


def test_neighbourhood_normal_bends_at_an_edge_and_shrinks_on_a_thin_wall():
    """On one face the mean normal is the face's; where a second face starts it bends towards it (the
    row at the edge, not three rows away); on a thin wall whose two sides face away from each other
    it shrinks; the same on a grid twice the size anywhere in the bin, and under bf16 autocast."""
    pts = _square_patch(7)
    up = torch.tensor([0.0, 0.0, 1.0]).expand(1, 49, 3)
    assert torch.allclose(neighbourhood_normal(pts, up, width=1.5), up, atol=1e-6)
    side = up.clone()
    side[:, 7:] = torch.tensor([1.0, 0.0, 0.0])  # a second face from row 1 on: row 0 sits at an edge
    bent = neighbourhood_normal(pts, side, width=1.5)
    edge, middle = 3, 24  # (0, 3) and (3, 3) of the 7 × 7 grid
    assert bent[0, edge, 0] > 0.3 and bent[0, middle, 0] > 0.9
    assert torch.allclose(neighbourhood_normal(2.0 * pts + 0.1, side, width=1.5), bent, atol=1e-5)
    # a wall 2 mm thick, its two sides sampled half a spacing apart (as a bowl's rim is, at random)
    wall = torch.cat([pts, pts + torch.tensor([0.005, 0.005, 0.002])], dim=1)
    sides = torch.cat([-up, up], dim=1)
    assert neighbourhood_normal(wall, sides, width=1.0)[0, 24].norm() < 0.5
    with torch.autocast("cpu", dtype=torch.bfloat16):  # computed in fp32 all the same
        assert torch.allclose(neighbourhood_normal(pts + 0.2, side, width=1.5), bent, atol=1e-4)


def test_neighbourhood_normal_input_variant():
    """``local_width`` adds the neighbourhood's mean normal to the object points' inputs: translation
    invariance and permutation equivariance hold, background rows get zeros, and the update's sparse
    encoding still matches the dense gradient."""
    torch.manual_seed(0)
    points, features = random_obs(3, 16, 8)
    normals = torch.nn.functional.normalize(torch.randn(3, 16, 3), dim=-1)
    enc = PointEncoder(16, 8, hidden=32, global_dim=32, out_dim=24, normals=True, local_width=1.5)
    assert enc.local[0].in_features == 13
    x = enc.normalise(points, features, normals)
    assert x.shape == (3, 24, 13) and torch.equal(x[:, 16:, 10:], torch.zeros(3, 8, 3))
    assert x[:, :16, 10:].abs().sum() > 0
    out = enc(points, features, normals)
    assert torch.allclose(enc(points + torch.tensor([0.2, -0.1, 0.0]), features, normals), out, atol=1e-4)
    perm = torch.randperm(16)
    order = torch.cat([perm, torch.arange(16, 24)])
    assert torch.allclose(
        enc(points[:, order], features[:, order], normals[:, perm]), out[:, perm], atol=1e-5
    )
    plain = PointEncoder(16, 8, hidden=32, global_dim=32, out_dim=24, normals=True)
    assert plain.local[0].in_features == 10
    with pytest.raises(ValueError, match="local_width"):
        PointEncoder(16, 8, normals=True, local_width=-1.0)
    with pytest.raises(ValueError, match="needs normals"):
        PointEncoder(16, 8, local_width=1.0)

    index = torch.randint(0, 16, (3,))
    ctx = enc.encode_context(points, features, normals)
    dense = enc.head(ctx.local[torch.arange(3), index], ctx.context)
    dense.sum().backward()
    dense_grads = [p.grad.clone() for p in enc.parameters()]
    enc.zero_grad()
    sparse, _ = enc.encode_for_update(points, features, normals, index)
    sparse.sum().backward()
    assert torch.allclose(sparse, dense, atol=1e-6)
    for got, want in zip([p.grad for p in enc.parameters()], dense_grads, strict=True):
        assert torch.allclose(got, want, atol=1e-5)
