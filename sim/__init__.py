"""hydo's simulator: native MuJoCo bin scene, object set, goals, observations, push primitive, env.

``import sim`` registers ``hydo/Bin-v0`` with gymnasium::

    import gymnasium, sim
    env = gymnasium.make("hydo/Bin-v0", goals="6d", objects="train", obs="mesh")

Never imports torch: deploy reuses ``sim.contract`` and ``sim.primitive`` without it.
"""

import os

# numpy in env code slows ~10x when its BLAS threads compete with torch (measurements.md).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# Offscreen rendering (rendered observations, videos) needs EGL chosen before mujoco is imported.
os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium  # noqa: E402

if "hydo/Bin-v0" not in gymnasium.registry:
    gymnasium.register(id="hydo/Bin-v0", entry_point="sim.env:BinEnv", disable_env_checker=True)
