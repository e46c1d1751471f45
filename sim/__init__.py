"""hydo's simulator: native MuJoCo bin scene, object set, goals, observations, push primitive, env.

``import sim`` does nothing heavy (no mujoco, no gymnasium): the contract modules
(``sim.contract``, ``sim.primitive``, ``sim.atomic``) are pure numpy, so the torch-free deploy path
and the learner may import them. ``import sim.env`` registers ``hydo/Bin-v0`` with gymnasium::

    import gymnasium, sim.env
    env = gymnasium.make("hydo/Bin-v0", goals="6d", objects="train", obs="mesh")

Never imports torch.
"""

import os

# numpy in env code slows ~10x when its BLAS threads compete with torch (measurements.md).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# Offscreen rendering (rendered observations, videos) needs EGL chosen before mujoco is imported.
os.environ.setdefault("MUJOCO_GL", "egl")
