"""ONNX export: parity with torch, the torch-free runner, and refusal of bad model folders."""

import json
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from hydo_cli.config import TrainConfig, agent_config
from hydo_cli.onnx_export import export_agent
from models.algos import HybridAgent
from robot.errors import InputError, ModelLoadError
from robot.onnx_policy import OnnxPolicy

TINY = dict(feature_dim=16, encoder_hidden=16, encoder_global=16, actor_hidden=16, critic_hidden=16)


@pytest.fixture(scope="module", params=["hydo-cm", "hacman"])
def exported(request, tmp_path_factory):
    cfg = TrainConfig(algo=request.param, objects="cube", n_obj=32, n_bg=16, agent=TINY)
    agent = HybridAgent(agent_config(cfg))
    out = tmp_path_factory.mktemp("export") / "model"
    report = export_agent(agent, cfg, "pytest", out, n_checks=32)
    return out, report, agent, cfg


def test_parity_and_manifest(exported):
    out, report, agent, cfg = exported
    assert report["max_abs_error_motion"] <= 1e-4 and report["max_abs_error_q"] <= 1e-4
    assert report["index_agreement"] == 1.0 and report["n"] == 32
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["algo"] == cfg.algo and manifest["n_obj"] == 32 and manifest["denoise_steps"] == 5
    assert set(manifest["sha256"]) == {"encoder.onnx", "actor.onnx", "critic.onnx"}
    import onnx

    props = {p.key: p.value for p in onnx.load(str(out / "actor.onnx")).metadata_props}
    assert json.loads(props["algo"]) == cfg.algo


def _export_with_parity(path, **agent_kw) -> dict:
    """Export a fresh tiny hydo-cm agent with ``agent_kw`` to ``path``: parity within the tolerance and
    the same argmax as torch. Returns the manifest."""
    cfg = TrainConfig(algo="hydo-cm", objects="cube", n_obj=32, n_bg=16, agent={**TINY, **agent_kw})
    report = export_agent(HybridAgent(agent_config(cfg)), cfg, "pytest", path, n_checks=32)
    assert report["max_abs_error_motion"] <= 1e-4 and report["max_abs_error_q"] <= 1e-4
    assert report["index_agreement"] == 1.0
    return json.loads((path / "manifest.json").read_text())


def test_the_manifest_names_the_contacts_a_model_was_trained_in(tmp_path):
    """Export records the run's contact model and eval reads it back (its note says how to match);
    a manifest from before the choice reads as the scene's own, an unknown model is refused."""
    from hydo_cli.policies import load_onnx_policy
    from robot.onnx_policy import read_manifest

    cfg = TrainConfig(algo="hydo-cm", objects="cube", n_obj=32, n_bg=16, agent=TINY, contacts="hacman")
    out = tmp_path / "model"
    export_agent(HybridAgent(agent_config(cfg)), cfg, "pytest", out, n_checks=8)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["contacts"] == "hacman"
    assert load_onnx_policy(out, seed=0).contacts == "hacman"
    del manifest["contacts"]
    (out / "manifest.json").write_text(json.dumps(manifest))
    assert load_onnx_policy(out, seed=0).contacts == "hydo"
    (out / "manifest.json").write_text(json.dumps({**manifest, "contacts": "rubber"}))
    with pytest.raises(ModelLoadError, match="contacts"):
        read_manifest(out)


def test_critic_motion_directions_export_with_parity(tmp_path):
    """The bilinear motion directions of the Q heads export with the same interface and tolerance."""
    _export_with_parity(tmp_path / "model", critic_motion_dirs=4)


def test_encoder_with_normals_exports_with_parity(tmp_path):
    """An agent trained with ``encoder_normals``: its encoder graph takes a third input, parity holds,
    the manifest lists the inputs, and the runner refuses to decide without normals."""
    manifest = _export_with_parity(tmp_path / "model", encoder_normals=True)
    assert manifest["encoder_inputs"] == ["points", "features", "normals"]
    policy = OnnxPolicy.load(tmp_path / "model")
    assert policy.needs_normals
    pts, feats = _observation()
    noise = policy.noise(1, np.random.default_rng(0))
    up = np.tile(np.float32([0, 0, 1]), (1, 32, 1))
    a = policy.decide(pts, feats, noise, up)
    b = policy.decide(pts, feats, noise, -up)
    assert not np.allclose(a["q"], b["q"])  # the normals reach the graph
    with pytest.raises(InputError, match="normals"):
        policy.decide(pts, feats, noise)


def _observation():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.1, 0.1, (1, 48, 3)).astype(np.float32)
    feats = np.zeros((1, 48, 4), np.float32)
    feats[:, :32, 0] = 1
    feats[:, :32, 1:] = rng.normal(0, 0.05, (1, 32, 3))
    return pts, feats


def test_fixed_noise_gives_identical_motions(exported):
    out, _, agent, cfg = exported
    policy = OnnxPolicy.load(out)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.1, 0.1, (2, 48, 3)).astype(np.float32)
    feats = np.zeros((2, 48, 4), np.float32)
    feats[:, :32, 0] = 1
    feats[:, :32, 1:] = rng.normal(0, 0.05, (2, 32, 3))
    noise = policy.noise(2, rng)
    normals = rng.normal(size=(2, 32, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    a = policy.decide(pts, feats, noise, normals)
    b = policy.decide(pts, feats, noise, normals)
    np.testing.assert_array_equal(a["motions"], b["motions"])
    assert np.all(np.abs(a["motions"]) <= 1.0)


def test_runner_imports_no_torch(exported, tmp_path):
    out = exported[0]
    script = textwrap.dedent(
        f"""
        import sys, importlib.abc
        class Block(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path, target=None):
                if name == "torch" or name.startswith("torch."):
                    raise ImportError("torch is blocked in this test")
        sys.meta_path.insert(0, Block())
        import numpy as np
        from robot.onnx_policy import OnnxPolicy
        p = OnnxPolicy.load({str(out)!r})
        n = p.n_obj + p.n_bg
        feats = np.zeros((n, 4), np.float32); feats[: p.n_obj, 0] = 1
        nrm = np.tile(np.float32([0, 0, 1]), (p.n_obj, 1))
        i, m, _ = p.act(np.random.default_rng(0).uniform(-0.1, 0.1, (n, 3)).astype(np.float32), feats,
                        np.random.default_rng(1), nrm)
        assert 0 <= i < p.n_obj and m.shape == (3,)
        assert "torch" not in sys.modules
        print("ok")
        """
    )
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr


def _copy(out, tmp_path):
    dst = tmp_path / "m"
    shutil.copytree(out, dst)
    return dst


def test_refuses_missing_file(exported, tmp_path):
    d = _copy(exported[0], tmp_path)
    (d / "critic.onnx").unlink()
    with pytest.raises(ModelLoadError, match="critic.onnx is missing"):
        OnnxPolicy.load(d)


def test_refuses_hash_mismatch(exported, tmp_path):
    d = _copy(exported[0], tmp_path)
    with open(d / "actor.onnx", "ab") as f:
        f.write(b"\0")
    with pytest.raises(ModelLoadError, match="sha256"):
        OnnxPolicy.load(d)


def test_refuses_truncated_onnx_even_with_matching_hash(exported, tmp_path):
    from robot.onnx_policy import sha256_file

    d = _copy(exported[0], tmp_path)
    data = (d / "encoder.onnx").read_bytes()
    (d / "encoder.onnx").write_bytes(data[: len(data) // 2])
    m = json.loads((d / "manifest.json").read_text())
    m["sha256"]["encoder.onnx"] = sha256_file(d / "encoder.onnx")
    (d / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ModelLoadError, match="cannot be loaded by onnxruntime"):
        OnnxPolicy.load(d)


def test_refuses_contract_mismatch_and_bad_manifest(exported, tmp_path):
    d = _copy(exported[0], tmp_path)
    m = json.loads((d / "manifest.json").read_text())
    m["obs_contract_version"] = 999
    (d / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ModelLoadError, match="observation contract"):
        OnnxPolicy.load(d)
    (d / "manifest.json").write_text("{not json")
    with pytest.raises(ModelLoadError, match="not valid JSON"):
        OnnxPolicy.load(d)
    with pytest.raises(ModelLoadError, match="does not exist"):
        OnnxPolicy.load(tmp_path / "nope")


def test_refuses_wrong_shapes_and_nans(exported):
    policy = OnnxPolicy.load(exported[0])
    rng = np.random.default_rng(0)
    with pytest.raises(InputError, match="points"):
        policy.act(np.zeros((10, 3), np.float32), np.zeros((48, 4), np.float32), rng)
    pts = np.zeros((48, 3), np.float32)
    pts[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        policy.act(pts, np.zeros((48, 4), np.float32), rng)


def test_cli_export_refuses_bad_checkpoint(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"garbage")
    r = subprocess.run(
        [
            sys.executable,
            "-c",
            "from hydo_cli.main import main; main()",
            "export",
            str(bad),
            "--out",
            str(tmp_path / "o"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 1 and "bad.pt" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "o").exists()


def test_onnx_policy_chooses_feasible_points(exported):
    """With the feasibility mask, the ONNX argmax runs over points whose push can run (as
    HybridAgent.act)."""
    from sim.env import BinEnv
    from sim.primitive import feasibility_mask, feasible_points

    policy = OnnxPolicy.load(exported[0])
    env = BinEnv("train", "planar", n_obj=policy.n_obj, n_bg=policy.n_bg)
    rng = np.random.default_rng(0)
    masked_rows = 0
    for ep in range(12):
        obs, _ = env.reset(seed=ep)
        pts, feats, nrm = obs["points"][None], obs["features"][None], obs["normals"][None]
        noise = policy.noise(1, rng)
        out = policy.decide(pts, feats, noise, nrm, feasibility_mask(pts, nrm))
        feasible = feasible_points(pts[:, : policy.n_obj], nrm, out["motions"], pts)
        if feasible.any():
            assert feasible[0, out["index"][0]]
        plain = policy.decide(pts, feats, noise, nrm)  # without a mask: the plain argmax of Q
        assert plain["index"][0] == out["q"].argmax(-1)[0]
        masked_rows += not feasible[0, plain["index"][0]]
    assert masked_rows > 0  # the mask changed at least one decision: the test has material
