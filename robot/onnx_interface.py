"""The ONNX interface of an exported policy: its one home (export writes it, deploy and eval read it).

Three graphs and a manifest, all in one folder::

    encoder.onnx   points (B, N, 3) float32 metres, features (B, N, 4) float32
                   [, normals (B, N_obj, 3) float32 unit: models trained with encoder_normals only;
                   the manifest's "encoder_inputs" lists the inputs]
                   -> point_features (B, N_obj, D): per-point features of the object points
    actor.onnx     point_features (B, M, D), noise (B, M, S, 3) standard normal
                   -> motion (B, M, 3) in [-1, 1]: the K-step sampler unrolled, its noise an input
    critic.onnx    point_features (B, M, D), motion (B, M, 3) -> q (B, M, 2): the twin critic
    manifest.json  contract version, point counts, K, noise schedule, algorithm, training command,
                   sha256 of each file (see ``MANIFEST_KEYS``)

Location choice (identical to training's ``eval`` mode): the object point with the highest Q of the
motion proposed at it, Q being the twin minimum for SAC variants and Q1 for TD3 variants
(``manifest["q_reduction"]``).
"""

from __future__ import annotations

from sim.contract import FEATURE_DIM, GOAL_MODES

FORMAT = "hydo-onnx/1"
FILES = ("encoder.onnx", "actor.onnx", "critic.onnx")
ENCODER_INPUTS = ("points", "features")
ENCODER_INPUTS_WITH_NORMALS = ("points", "features", "normals")
ENCODER_OUTPUTS = ("point_features",)
ACTOR_INPUTS = ("point_features", "noise")
ACTOR_OUTPUTS = ("motion",)
CRITIC_INPUTS = ("point_features", "motion")
CRITIC_OUTPUTS = ("q",)
MANIFEST_KEYS = (
    "format",
    "obs_contract_version",
    "algo",
    "n_obj",
    "n_bg",
    "feature_dim",
    "denoise_steps",
    "noise_per_point",  # S: standard-normal 3-vectors per point the actor consumes
    "noise_schedule",
    "q_reduction",  # "min" (SAC) | "q1" (TD3)
    "stochastic",  # whether the actor's output depends on its noise
    "goals",  # "planar" | "6d": how deploy registers the object to its goal (never guessed)
    "training_command",
    "sha256",
)
Q_REDUCTIONS = ("min", "q1")
#: dtype of every graph input and output, as onnxruntime names it
TENSOR_TYPE = "tensor(float)"


# --- validation: the one home of "is this folder an exported hydo model" ------------------------------
# Pure Python on what the manifest says and what onnxruntime reports of each graph (``NodeArg``: name,
# shape, type), so export's own check and deploy/eval's load refuse exactly the same things.


class InterfaceError(ValueError):
    """A manifest or graph that breaks the interface above; the message names the file and the field."""


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def check_manifest(manifest, source: str) -> None:
    """Refuse a manifest whose fields are missing, of the wrong type or an unknown enum value.

    Never read a missing or unknown value as a default (a manifest without ``goals`` is not a 6D
    model, an unknown ``q_reduction`` is not Q1): ``InterfaceError`` naming the key instead.
    """
    if not isinstance(manifest, dict):
        raise InterfaceError(f"{source} is not a JSON object (got {type(manifest).__name__})")
    missing = [k for k in MANIFEST_KEYS if k not in manifest]
    if missing:
        raise InterfaceError(f"{source} lacks {missing}: re-export the model")

    def bad(key: str, want: str) -> InterfaceError:
        return InterfaceError(f"{source}: `{key}` must be {want}, got {manifest[key]!r}")

    for key in ("format", "algo", "training_command"):
        if not isinstance(manifest[key], str) or (key != "training_command" and not manifest[key]):
            raise bad(key, "a non-empty string" if key != "training_command" else "a string")
    if not _is_int(manifest["obs_contract_version"]):
        raise bad("obs_contract_version", "an integer")
    for key in ("n_obj", "n_bg", "feature_dim", "noise_per_point"):
        if not _is_int(manifest[key]) or manifest[key] < 1:
            raise bad(key, "an integer >= 1")
    if not _is_int(manifest["denoise_steps"]) or manifest["denoise_steps"] < 0:
        raise bad("denoise_steps", "an integer >= 0")
    if not isinstance(manifest["noise_schedule"], dict):
        raise bad("noise_schedule", "a JSON object")
    if manifest["q_reduction"] not in Q_REDUCTIONS:
        raise bad("q_reduction", f"one of {list(Q_REDUCTIONS)}")
    if not isinstance(manifest["stochastic"], bool):
        raise bad("stochastic", "true or false")
    if manifest["goals"] not in GOAL_MODES:
        raise bad("goals", f"one of {list(GOAL_MODES)}")
    if "objects" in manifest and not (isinstance(manifest["objects"], str) and manifest["objects"]):
        raise bad("objects", "a non-empty string (an object set or mesh path)")
    inputs = manifest.get("encoder_inputs")  # absent in exports before encoder normals existed
    if inputs is not None and tuple(inputs) not in (ENCODER_INPUTS, ENCODER_INPUTS_WITH_NORMALS):
        raise bad("encoder_inputs", f"{list(ENCODER_INPUTS)} or {list(ENCODER_INPUTS_WITH_NORMALS)}")
    sha = manifest["sha256"]
    if not isinstance(sha, dict) or sorted(sha) != sorted(FILES):
        raise bad("sha256", f"an object with one hash per graph {list(FILES)}")
    for name, h in sha.items():
        if not (isinstance(h, str) and len(h) == 64 and all(c in "0123456789abcdef" for c in h)):
            raise InterfaceError(f"{source}: `sha256.{name}` must be 64 hex digits, got {h!r}")


def graph_spec(manifest: dict, name: str, with_normals: bool):
    """``(inputs, outputs)`` of graph ``name`` as ``[(tensor name, shape)]``; a shape's entry is an int
    (fixed by the manifest) or None (free: batch, and the point count of actor and critic)."""
    n_obj, n_bg = manifest["n_obj"], manifest["n_bg"]
    d, s = manifest["feature_dim"], manifest["noise_per_point"]
    n = n_obj + n_bg
    if name == "encoder.onnx":
        ins = [("points", (None, n, 3)), ("features", (None, n, FEATURE_DIM))]
        if with_normals:
            ins.append(("normals", (None, n_obj, 3)))
        return ins, [("point_features", (None, n_obj, d))]
    if name == "actor.onnx":
        return [("point_features", (None, None, d)), ("noise", (None, None, s, 3))], [
            ("motion", (None, None, 3))
        ]
    if name == "critic.onnx":
        return [("point_features", (None, None, d)), ("motion", (None, None, 3))], [("q", (None, None, 2))]
    raise KeyError(name)


def check_graph(path: str, name: str, manifest: dict, inputs, outputs) -> None:
    """Refuse a graph whose input/output names, ranks, fixed sizes or dtypes are not ``name``'s in this
    interface for ``manifest``. ``inputs`` / ``outputs``: onnxruntime's ``NodeArg`` lists (``.name``,
    ``.shape``: ints for fixed sizes, strings or None for free ones, ``.type``). A graph swapped with
    another file is refused here even when its hash was rewritten to match."""
    in_names = tuple(i.name for i in inputs)
    with_normals = in_names == ENCODER_INPUTS_WITH_NORMALS
    want_in, want_out = graph_spec(manifest, name, with_normals)
    enc_inputs = manifest.get("encoder_inputs")
    if name == "encoder.onnx" and enc_inputs is not None and tuple(enc_inputs) != in_names:
        raise InterfaceError(
            f"{path}: inputs {list(in_names)}, the manifest's `encoder_inputs` says {list(enc_inputs)}"
        )
    for kind, got, want in (("inputs", inputs, want_in), ("outputs", outputs, want_out)):
        names = [g.name for g in got]
        if names != [w[0] for w in want]:
            raise InterfaceError(
                f"{path}: {kind} {names}, the interface of {name} is {[w[0] for w in want]} "
                "(a graph from another file, or not a hydo export)"
            )
        for g, (tensor, shape) in zip(got, want, strict=True):
            if g.type != TENSOR_TYPE:
                raise InterfaceError(f"{path}: `{tensor}` is {g.type}, the interface says {TENSOR_TYPE}")
            gshape = list(g.shape or [])
            if len(gshape) != len(shape):
                raise InterfaceError(
                    f"{path}: `{tensor}` has rank {len(gshape)} {gshape}, the interface says rank {len(shape)}"
                )
            for axis, (have, need) in enumerate(zip(gshape, shape, strict=True)):
                if need is not None and isinstance(have, int) and have != need:
                    raise InterfaceError(
                        f"{path}: `{tensor}` axis {axis} is {have}, the sizes in manifest.json (n_obj, n_bg, "
                        f"feature_dim, noise_per_point) give {need} (shape {gshape}, expected {list(shape)})"
                    )
