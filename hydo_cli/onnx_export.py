"""Writing an agent as verified ONNX (``robot.onnx_interface``): one home for ``hydo export``, the
benches and the tests.

The export is written to a temporary folder beside ``out``, verified there — ``onnx.checker`` with
``full_check``, then onnxruntime against torch on random and real observations with the same noise
(max abs error ≤ 1e-4 on motions and Q; the selected point is torch's, or ties it within 1e-4) — and
only then renamed into place. A failed verification leaves no model folder behind.
"""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np

from hydo_cli.errors import HydoError

TOLERANCE = 1e-4  # max abs difference torch vs onnxruntime on motions and Q
OPSET = 18


#: Known exporter messages that say nothing about this export; each was checked (torch 2.x dynamo
#: exporter) and is silenced only around ``torch.onnx.export``. Anything else still prints.
KNOWN_EXPORT_WARNINGS = (
    # hydo's graphs hold no train/eval-dependent layer (no dropout, no batch norm, no ``.training``
    # branch in models/), and ``verify`` compares onnxruntime with torch after the export anyway
    (UserWarning, r"Exporting a model while it is in training mode"),
    # the dynamic axes share one name on purpose (every input's batch is the same batch)
    (UserWarning, r"# The axis name: \w+ will not be used, since it shares the same shape constraints"),
    # a deprecation inside torch's own pytree code, not in hydo
    (FutureWarning, r"`isinstance\(treespec, LeafSpec\)` is deprecated"),
)
#: torch's exporter logs one line per torchvision operator it cannot register; hydo uses none
_TORCHVISION_LOGGER = "torch.onnx._internal.exporter._registration"


class _DropTorchvisionNotice(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return "torchvision is not installed" not in record.getMessage()


@contextlib.contextmanager
def _quiet_exporter():
    """Silence exactly ``KNOWN_EXPORT_WARNINGS`` and the torchvision notices while exporting."""
    logger = logging.getLogger(_TORCHVISION_LOGGER)
    drop = _DropTorchvisionNotice()
    logger.addFilter(drop)
    try:
        with warnings.catch_warnings():
            for category, message in KNOWN_EXPORT_WARNINGS:
                warnings.filterwarnings("ignore", message=message, category=category)
            yield
    finally:
        logger.removeFilter(drop)


def _export_one(torch, module, args, names_in, names_out, path, dynamic):
    try:
        with _quiet_exporter():
            torch.onnx.export(
                module,
                args,
                str(path),
                input_names=list(names_in),
                output_names=list(names_out),
                dynamic_shapes=dynamic,
                opset_version=OPSET,
                dynamo=True,
                external_data=False,
                verbose=False,
            )
    except Exception as e:
        raise HydoError(f"torch.onnx.export failed for {path.name}: {str(e).splitlines()[0]}") from None


def _real_observations(cfg, n: int, seed: int):
    """``n`` observations from the training env configuration (goals, objects, contacts)."""
    from hydo_cli.envs import make_envs
    from sim.baselines import random_action

    env = make_envs(
        cfg.objects, cfg.goals, cfg.clutter, "mesh", 1, cfg.n_obj, cfg.n_bg, contacts=cfg.contacts
    )[0]
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    out = []
    while len(out) < n:
        out.append(obs)
        obs, _, term, trunc, _ = env.step(random_action(obs, rng))
        if term or trunc:
            obs, _ = env.reset(seed=int(rng.integers(2**31)))
    return out


def verify(folder: Path, agent, graphs, torch, observations, rng: np.random.Generator) -> dict:
    """onnxruntime vs the exported torch ``graphs`` (``models.export.export_modules``, which decide as
    ``hydo eval`` does: tests/models/test_algos.py) on ``observations`` (list of (points, features,
    normals)), fed the same noise; raise on mismatch."""
    from robot.onnx_policy import OnnxPolicy

    policy = OnnxPolicy.load(folder)
    max_motion, max_q, agree = 0.0, 0.0, 0
    for points, features, normals in observations:
        noise = policy.noise(points.shape[0], rng)
        ort = policy.decide(points, features, noise, normals)
        with torch.no_grad():
            enc_args = [torch.from_numpy(points), torch.from_numpy(features)]
            if agent.config.encoder_normals:
                enc_args.append(torch.from_numpy(normals))
            f = graphs["encoder"](*enc_args)
            motions = graphs["actor"](f, torch.from_numpy(noise))
            q = agent.decision_q(graphs["critic"](f, motions))
        max_motion = max(max_motion, float(np.abs(ort["motions"] - motions.numpy()).max()))
        max_q = max(max_q, float(np.abs(ort["q"] - q.numpy()).max()))
        # Same point, or a point whose torch Q ties the best within the tolerance (an untrained
        # critic may score points within ~1e-6: rounding may break the tie either way).
        q_np = q.numpy()
        rows = np.arange(q_np.shape[0])
        agree += int(np.sum(q_np.max(-1) - q_np[rows, ort["index"]] <= TOLERANCE))
    total = sum(p.shape[0] for p, _, _ in observations)
    report = {
        "max_abs_error_motion": max_motion,
        "max_abs_error_q": max_q,
        "index_agreement": agree / total,
        "n": total,
    }
    if max_motion > TOLERANCE or max_q > TOLERANCE:
        raise HydoError(
            f"export verification failed: max abs error motion {max_motion:.2e}, Q {max_q:.2e} > {TOLERANCE:.0e}"
        )
    if agree != total:
        raise HydoError(
            f"export verification failed: onnxruntime selected a different point in {total - agree} of {total} observations"
        )
    return report


def export_agent(agent, cfg, command: str, out: Path, seed: int = 0, n_checks: int = 128) -> dict:
    """Export ``agent`` (trained with ``cfg``) to ``out``; returns the verification report."""
    import onnx
    import torch

    from models.export import export_modules
    from robot.onnx_interface import (
        ACTOR_INPUTS,
        ACTOR_OUTPUTS,
        CRITIC_INPUTS,
        CRITIC_OUTPUTS,
        ENCODER_INPUTS,
        ENCODER_INPUTS_WITH_NORMALS,
        ENCODER_OUTPUTS,
        FILES,
        FORMAT,
    )
    from robot.onnx_policy import sha256_file
    from sim.contract import FEATURE_DIM, OBS_CONTRACT_VERSION

    graphs = export_modules(agent)
    enc, act, cri = graphs["encoder"], graphs["actor"], graphs["critic"]
    n = cfg.n_obj + cfg.n_bg
    d = agent.config.feature_dim
    s = agent.motion_policy.n_noise
    b = 2
    gen = torch.Generator().manual_seed(seed)
    points = torch.rand(b, n, 3, generator=gen) * 0.3
    features = torch.zeros(b, n, FEATURE_DIM)
    features[:, : cfg.n_obj, 0] = 1.0
    normals = torch.nn.functional.normalize(torch.randn(b, cfg.n_obj, 3, generator=gen), dim=-1)
    pf = torch.randn(b, cfg.n_obj, d, generator=gen)
    noise = torch.randn(b, cfg.n_obj, s, 3, generator=gen)
    motion = torch.rand(b, cfg.n_obj, 3, generator=gen) * 2 - 1
    batch = torch.export.Dim("batch", min=1, max=4096)
    m_pts = torch.export.Dim("points", min=1, max=100_000)

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}."))
    try:
        with_normals = agent.config.encoder_normals
        _export_one(
            torch,
            enc,
            (points, features, normals) if with_normals else (points, features),
            ENCODER_INPUTS_WITH_NORMALS if with_normals else ENCODER_INPUTS,
            ENCODER_OUTPUTS,
            tmp / FILES[0],
            {"points": {0: batch}, "features": {0: batch}}
            | ({"normals": {0: batch}} if with_normals else {}),
        )
        _export_one(
            torch,
            act,
            (pf, noise),
            ACTOR_INPUTS,
            ACTOR_OUTPUTS,
            tmp / FILES[1],
            {"point_features": {0: batch, 1: m_pts}, "noise": {0: batch, 1: m_pts}},
        )
        _export_one(
            torch,
            cri,
            (pf, motion),
            CRITIC_INPUTS,
            CRITIC_OUTPUTS,
            tmp / FILES[2],
            {"point_features": {0: batch, 1: m_pts}, "motion": {0: batch, 1: m_pts}},
        )
        spec = agent.spec
        schedule = agent.config.to_dict()
        manifest = {
            "format": FORMAT,
            "obs_contract_version": OBS_CONTRACT_VERSION,
            "algo": cfg.algo,
            "paper_name": spec.paper_name,
            "n_obj": cfg.n_obj,
            "n_bg": cfg.n_bg,
            "feature_dim": d,
            "encoder_inputs": list(ENCODER_INPUTS_WITH_NORMALS if with_normals else ENCODER_INPUTS),
            "denoise_steps": agent.config.denoise_steps,
            "noise_per_point": s,
            "noise_schedule": {
                k: v for k, v in schedule.items() if k.startswith(("ddpm_", "cm_", "final_std", "chain_"))
            },
            "q_reduction": "min" if agent.is_sac else "q1",
            "stochastic": bool(agent.eval_stochastic),
            "goals": cfg.goals,
            "objects": cfg.objects,
            "contacts": cfg.contacts,
            "training_command": command,
            "agent_config": schedule,
        }
        # ONNX metadata carries the same key facts, so a lone .onnx file still says what it is.
        props = {
            k: json.dumps(manifest[k])
            for k in (
                "format",
                "obs_contract_version",
                "algo",
                "n_obj",
                "n_bg",
                "denoise_steps",
                "q_reduction",
                "stochastic",
            )
        }
        for name in FILES:
            model = onnx.load(str(tmp / name))
            onnx.helper.set_model_props(model, props)
            onnx.save(model, str(tmp / name))
            try:
                onnx.checker.check_model(model, full_check=True)
            except Exception as e:
                raise HydoError(f"onnx.checker rejected {name}: {str(e).splitlines()[0]}") from None
        manifest["sha256"] = {name: sha256_file(tmp / name) for name in FILES}
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2))
        rng = np.random.default_rng(seed)
        real = _real_observations(cfg, n_checks // 2, seed)
        checks = [tuple(np.stack([o[k] for o in real]) for k in ("points", "features", "normals"))]
        rnd = []
        for _ in range(n_checks - n_checks // 2):
            o = real[int(rng.integers(len(real)))]
            p = (o["points"] + rng.normal(0, 0.01, o["points"].shape)).astype(np.float32)
            f = o["features"].copy()
            f[: cfg.n_obj, 1:] = rng.normal(0, 0.1, (cfg.n_obj, 3)).astype(np.float32)
            rnd.append((p, f, o["normals"]))
        checks.append(tuple(np.stack([r[j] for r in rnd]) for j in range(3)))
        report = verify(tmp, agent, graphs, torch, checks, rng)
        manifest["verification"] = report
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2))
        tmp.chmod(0o755)  # mkdtemp makes it private; a model folder is meant to be shared
        for f in tmp.iterdir():
            f.chmod(0o644)
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
        return report
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
