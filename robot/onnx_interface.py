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
    "training_command",
    "sha256",
)
