import os

# Rendering tests need EGL selected before mujoco is first imported; numpy must not fight torch.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
