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

from typing import Annotated, Any, Literal

from pydantic import BaseModel, Field, ValidationError, model_validator

from models.choices import ALGOS
from sim.contract import CONTACT_DEFAULT, CONTACT_MODELS, FEATURE_DIM, GOAL_MODES
from sim.schema import STRICT, one_line

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


#: Keys an export writes beside ``MANIFEST_KEYS`` (records, cross-checked where they say the same).
OPTIONAL_KEYS = ("paper_name", "objects", "contacts", "encoder_inputs", "agent_config", "verification")
#: ``metadata_props`` the exporter stores in each graph (JSON values): what a lone .onnx says it is.
GRAPH_METADATA = ("format", "obs_contract_version", "algo", "n_obj", "n_bg", "denoise_steps", "q_reduction")
#: Schedule keys (``noise_schedule``) and the AgentConfig fields they copy.
SCHEDULE_KEYS = (
    "chain_entropy",
    "final_std",
    "ddpm_beta_min",
    "ddpm_beta_max",
    "cm_sigma_max",
    "cm_sigma_min",
    "cm_sigma_data",
    "cm_rho",
)
#: agent_config fields that must equal the manifest's own keys of the same name.
AGENT_CONFIG_SHARED = ("algo", "n_obj", "n_bg", "feature_dim", "denoise_steps")

_Positive = Annotated[float, Field(gt=0)]
_Count = Annotated[int, Field(ge=1)]
_Hex64 = Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]


class NoiseSchedule(BaseModel):
    """``noise_schedule``: the chain's fixed noise levels (AgentConfig's fields of the same names)."""

    model_config = STRICT

    chain_entropy: Literal["bound", "learned_std"]
    final_std: _Positive
    ddpm_beta_min: _Positive
    ddpm_beta_max: _Positive
    cm_sigma_max: _Positive
    cm_sigma_min: _Positive
    cm_sigma_data: _Positive
    cm_rho: _Positive

    @model_validator(mode="after")
    def _ordered(self) -> NoiseSchedule:
        if not self.ddpm_beta_min < self.ddpm_beta_max:
            raise ValueError(
                f"ddpm_beta_min {self.ddpm_beta_min} must be below ddpm_beta_max {self.ddpm_beta_max}"
            )
        if not self.cm_sigma_min < self.cm_sigma_max:
            raise ValueError(
                f"cm_sigma_min {self.cm_sigma_min} must be below cm_sigma_max {self.cm_sigma_max}"
            )
        return self


class Manifest(BaseModel):
    """``manifest.json``: every key typed and ranged, and the keys checked against each other and
    against the algorithm table (``models.choices.ALGOS``, torch-free): the noise a chain of K steps
    consumes, the Q reduction of the objective, the paper name, the agent record."""

    model_config = STRICT

    format: Annotated[str, Field(min_length=1)]
    obs_contract_version: int
    algo: Literal[tuple(ALGOS)]  # type: ignore[valid-type]
    n_obj: _Count
    n_bg: _Count
    feature_dim: _Count
    denoise_steps: _Count
    noise_per_point: _Count
    noise_schedule: NoiseSchedule
    q_reduction: Literal[Q_REDUCTIONS]  # type: ignore[valid-type]
    stochastic: bool
    goals: Literal[GOAL_MODES]  # type: ignore[valid-type]
    training_command: str
    sha256: dict[Literal[FILES], _Hex64]  # type: ignore[valid-type]
    paper_name: str | None = None
    objects: Annotated[str, Field(min_length=1)] | None = None
    # The scene's contact model it was trained in; absent in exports made before there was a choice,
    # which were all trained in ``sim.contract.CONTACT_DEFAULT``.
    contacts: Literal[CONTACT_MODELS] | None = None  # type: ignore[valid-type]
    encoder_inputs: list[str] | None = None  # absent in exports before encoder normals existed
    agent_config: dict[str, Any] | None = None
    verification: dict[str, Any] | None = None

    @model_validator(mode="after")
    def _agree(self) -> Manifest:
        spec = ALGOS[self.algo]
        if sorted(self.sha256) != sorted(FILES):
            raise ValueError(
                f"`sha256` must hold one hash per graph {list(FILES)}, got {sorted(self.sha256)}"
            )
        # The actor's noise input is (B, M, S, 3): a K-step chain draws u^K and one z per step, a
        # tanh / Gaussian policy one 3-vector. So K is read off the graph (check_graph checks S).
        want_s = self.denoise_steps + 1 if spec.motion in ("ddpm", "cm") else 1
        if self.noise_per_point != want_s:
            if want_s > 1:
                why = (
                    f"a {spec.motion} chain of K steps takes K + 1 noise draws per point, so the actor's "
                    f"{self.noise_per_point} say K = {self.noise_per_point - 1}"
                )
            else:
                why = f"{self.algo}'s {spec.motion} policy takes 1 noise draw per point"
            raise ValueError(
                f"`denoise_steps` {self.denoise_steps} disagrees with `noise_per_point` {self.noise_per_point}: {why}"
            )
        want_q = "min" if spec.objective == "sac" else "q1"
        if self.q_reduction != want_q:
            raise ValueError(
                f"`q_reduction` {self.q_reduction!r} is not {self.algo}'s ({spec.objective}: {want_q!r})"
            )
        if spec.motion in ("tanh", "gauss") and self.stochastic:
            raise ValueError(
                f"`stochastic` is true, but {self.algo}'s {spec.motion} policy acts deterministically"
            )
        if self.paper_name is not None and self.paper_name != spec.paper_name:
            raise ValueError(f"`paper_name` {self.paper_name!r} is not {self.algo}'s ({spec.paper_name!r})")
        if self.encoder_inputs is not None and tuple(self.encoder_inputs) not in (
            ENCODER_INPUTS,
            ENCODER_INPUTS_WITH_NORMALS,
        ):
            raise ValueError(
                f"`encoder_inputs` must be {list(ENCODER_INPUTS)} or {list(ENCODER_INPUTS_WITH_NORMALS)}, "
                f"got {self.encoder_inputs}"
            )
        agent = self.agent_config
        if agent is not None:
            for key in (*AGENT_CONFIG_SHARED, *SCHEDULE_KEYS):
                mine = getattr(self.noise_schedule, key) if key in SCHEDULE_KEYS else getattr(self, key)
                where = f"noise_schedule.{key}" if key in SCHEDULE_KEYS else key
                if key in agent and agent[key] != mine:
                    raise ValueError(f"`{where}` {mine!r} disagrees with `agent_config.{key}` {agent[key]!r}")
            normals = agent.get("encoder_normals")
            if self.encoder_inputs is not None and normals is not None:
                if normals != (tuple(self.encoder_inputs) == ENCODER_INPUTS_WITH_NORMALS):
                    raise ValueError(
                        f"`encoder_inputs` {self.encoder_inputs} disagrees with `agent_config.encoder_normals` {normals}"
                    )
        return self


def manifest_contacts(manifest: dict) -> str:
    """The contact model a checked manifest's policy was trained in (``CONTACT_MODELS``); exports made
    before the key existed were all trained in ``CONTACT_DEFAULT``."""
    return str(manifest.get("contacts") or CONTACT_DEFAULT)


def check_manifest(manifest, source: str) -> None:
    """Refuse a manifest whose fields are missing, unknown, of the wrong type or range, an unknown enum
    value, or that disagree with each other (:class:`Manifest`).

    Never read a missing or unknown value as a default (a manifest without ``goals`` is not a 6D
    model, an unknown ``q_reduction`` is not Q1): ``InterfaceError`` naming the key instead.
    """
    if not isinstance(manifest, dict):
        raise InterfaceError(f"{source} is not a JSON object (got {type(manifest).__name__})")
    missing = [k for k in MANIFEST_KEYS if k not in manifest]
    if missing:
        raise InterfaceError(f"{source} lacks {missing}: re-export the model")
    try:
        Manifest(**manifest)
    except ValidationError as e:
        raise InterfaceError(one_line(e, source)) from None


def check_metadata(path: str, manifest: dict, metadata: dict[str, str]) -> None:
    """Refuse a graph whose ``metadata_props`` (what the exporter recorded in it: algorithm, point
    counts, K, ...) disagree with the manifest beside it. Graphs exported before the metadata existed
    carry none; their K is still checked through the noise input's shape (``Manifest``, ``check_graph``)."""
    import json

    for key in GRAPH_METADATA:
        if key not in metadata:
            continue
        try:
            value = json.loads(metadata[key])
        except ValueError:
            raise InterfaceError(
                f"{path}: metadata `{key}` is not JSON, got {metadata[key][:40]!r}"
            ) from None
        if value != manifest[key]:
            raise InterfaceError(
                f"{path}: the graph was exported with `{key}` = {value!r}, manifest.json says {manifest[key]!r}"
            )


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
