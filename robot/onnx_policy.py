"""Run an exported policy with onnxruntime: numpy in, action out, no torch.

    policy = OnnxPolicy.load("models/hydo-cm-planar")      # refuses bad folders with one line
    index, motion, info = policy.act(points, features, rng)

Loading checks, before any device opens: every file present, the manifest's fields, types and enum
values (``robot.onnx_interface.check_manifest``), format and observation-contract versions, sha256 of
every graph, that onnxruntime can parse each graph, and each graph's input and output names, shapes
and dtypes against the interface and the manifest's point counts (``check_graph``). ``act`` checks shapes and finiteness of its inputs and of the
network's outputs.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robot.errors import InputError, ModelLoadError
from robot.onnx_interface import FILES, FORMAT, InterfaceError, check_graph, check_manifest, check_metadata
from sim.contract import FEATURE_DIM, OBS_CONTRACT_VERSION
from sim.primitive import FeasibilityMask


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def read_manifest(folder: Path) -> dict:
    """Load and validate ``manifest.json`` and the graphs' hashes; raise ``ModelLoadError`` (one line)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ModelLoadError(f"model folder {folder} does not exist")
    mpath = folder / "manifest.json"
    if not mpath.exists():
        raise ModelLoadError(f"{mpath} is missing: not an exported hydo model (run `hydo export` first)")
    try:
        manifest = json.loads(mpath.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ModelLoadError(
            f"{mpath} is not valid JSON ({e.__class__.__name__}): re-export the model"
        ) from None
    except OSError as e:
        raise ModelLoadError(f"{mpath} cannot be read ({e.strerror or e.__class__.__name__})") from None
    # versions first: a model of another hydo is named as such, not as a list of odd fields
    if isinstance(manifest, dict) and manifest.get("format", FORMAT) != FORMAT:
        raise ModelLoadError(f"{mpath}: format {manifest['format']!r}, this hydo reads {FORMAT!r}")
    if (
        isinstance(manifest, dict)
        and manifest.get("obs_contract_version", OBS_CONTRACT_VERSION) != OBS_CONTRACT_VERSION
    ):
        raise ModelLoadError(
            f"{mpath}: observation contract v{manifest['obs_contract_version']}, this hydo builds "
            f"v{OBS_CONTRACT_VERSION} observations: re-export with this version"
        )
    try:
        check_manifest(manifest, str(mpath))
    except InterfaceError as e:
        raise ModelLoadError(str(e)) from None
    for name in FILES:
        f = folder / name
        if not f.exists():
            raise ModelLoadError(f"{f} is missing")
        want = manifest["sha256"].get(name)
        got = sha256_file(f)
        if want != got:
            raise ModelLoadError(
                f"{f}: sha256 {got[:12]}... does not match the manifest's {str(want)[:12]}..."
            )
    return manifest


@dataclass
class OnnxPolicy:
    """The exported encoder, actor and critic as onnxruntime sessions, plus the manifest."""

    manifest: dict
    encoder: object
    actor: object
    critic: object

    @classmethod
    def load(cls, folder: Path | str, threads: int = 2) -> OnnxPolicy:
        import onnxruntime as ort

        folder = Path(folder)
        manifest = read_manifest(folder)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        # Spinning threads slow everything else in the process by ~1.5x (measurements.md).
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        sessions = []
        for name in FILES:
            try:
                sessions.append(
                    ort.InferenceSession(str(folder / name), opts, providers=["CPUExecutionProvider"])
                )
            except Exception as e:  # onnxruntime raises its own Fail/InvalidProtobuf types
                first = (str(e).strip().splitlines() or [e.__class__.__name__])[0]
                raise ModelLoadError(
                    f"{folder / name} cannot be loaded by onnxruntime (not an ONNX graph?): {first[:200]}"
                ) from None
            try:  # the hash only says the file is the one exported; this says it is the right graph
                check_graph(
                    str(folder / name), name, manifest, sessions[-1].get_inputs(), sessions[-1].get_outputs()
                )
                check_metadata(str(folder / name), manifest, sessions[-1].get_modelmeta().custom_metadata_map)
            except InterfaceError as e:
                raise ModelLoadError(str(e)) from None
        return cls(manifest, *sessions)

    @property
    def n_obj(self) -> int:
        return int(self.manifest["n_obj"])

    @property
    def n_bg(self) -> int:
        return int(self.manifest["n_bg"])

    @property
    def stochastic(self) -> bool:
        return bool(self.manifest["stochastic"])

    @property
    def needs_normals(self) -> bool:
        """Whether the encoder takes the object points' normals (a model trained with encoder_normals)."""
        return "normals" in [i.name for i in self.encoder.get_inputs()]

    def check_inputs(self, points: np.ndarray, features: np.ndarray) -> None:
        n = self.n_obj + self.n_bg
        for name, a, shape in (("points", points, (n, 3)), ("features", features, (n, FEATURE_DIM))):
            a = np.asarray(a)
            if a.shape != shape and a.shape[1:] != shape:
                raise InputError(
                    f"`{name}` has shape {a.shape}, this model expects {shape} (or (B, *{shape}))"
                )
            if not np.all(np.isfinite(a)):
                raise InputError(f"`{name}` contains NaN or inf")

    def decide(
        self,
        points: np.ndarray,
        features: np.ndarray,
        noise: np.ndarray,
        normals: np.ndarray | None = None,
        feasible: FeasibilityMask | None = None,
    ) -> dict[str, np.ndarray]:
        """One batched decision. ``points (B, N, 3)``, ``features (B, N, 4)``, ``noise (B, N_obj, S, 3)``.

        ``feasible``: the feasibility mask made where the observation was made
        (``sim.primitive.feasibility_mask``, with the cell's workspace and bin); the argmax then runs
        over the points whose proposed push can run, as ``HybridAgent.act``. None: over every object
        point. A model whose encoder takes the object points' ``normals (B, N_obj, 3)``
        (``needs_normals``) refuses to decide without them.

        Returns ``index (B,)``, ``motion (B, 3)``, ``motions (B, N_obj, 3)``, ``q (B, N_obj)``.
        """
        self.check_inputs(points, features)
        inputs = {"points": points.astype(np.float32), "features": features.astype(np.float32)}
        if normals is not None:
            normals = np.asarray(normals, dtype=np.float32)
            want = (points.shape[0], self.n_obj, 3)
            if normals.shape != want or not np.all(np.isfinite(normals)):
                raise InputError(f"`normals` must be finite with shape {want}, got {normals.shape}")
        if self.needs_normals:
            if normals is None:
                raise InputError("this model's encoder takes the object points' normals: pass `normals`")
            inputs["normals"] = normals
        pf = self.encoder.run(None, inputs)[0]
        motions = self.actor.run(None, {"point_features": pf, "noise": noise.astype(np.float32)})[0]
        q_twin = self.critic.run(None, {"point_features": pf, "motion": motions})[0]
        if not (np.all(np.isfinite(motions)) and np.all(np.isfinite(q_twin))):
            raise InputError("the policy produced NaN or inf (motion or Q): refusing to act")
        q = q_twin.min(-1) if self.manifest["q_reduction"] == "min" else q_twin[..., 0]
        q_select = q if feasible is None else np.where(feasible(motions), q, -np.inf)
        index = q_select.argmax(-1)
        rows = np.arange(len(index))
        return {"index": index, "motion": motions[rows, index], "motions": motions, "q": q}

    def noise(self, batch: int, rng: np.random.Generator) -> np.ndarray:
        """Standard-normal actor noise ``(B, N_obj, S, 3)`` float32."""
        return rng.standard_normal((batch, self.n_obj, int(self.manifest["noise_per_point"]), 3)).astype(
            np.float32
        )

    def act(
        self,
        points: np.ndarray,
        features: np.ndarray,
        rng: np.random.Generator,
        normals: np.ndarray | None = None,
        feasible: FeasibilityMask | None = None,
    ):
        """One observation (``points (N, 3)``, ``features (N, 4)``, optional ``normals (N_obj, 3)``, and
        ``feasible`` made for the batch of one) → ``(index, motion (3,), info)``."""
        nrm = None if normals is None else np.asarray(normals)[None]
        out = self.decide(points[None], features[None], self.noise(1, rng), nrm, feasible)
        return int(out["index"][0]), out["motion"][0], {k: v[0] for k, v in out.items()}
