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
