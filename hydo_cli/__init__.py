"""hydo's command line: ``hydo train | eval | export | deploy``. Start reading at ``main.py``."""

import os

# Set before torch is imported. With the default (active) OpenMP wait policy, torch's 2 threads
# spin-wait for each other; when anything else runs on this 2-core machine (an env, a second run,
# the renderer) the spinning starves it and a decision took 30x longer (0.4 vs 14.7 eval episodes/s
# measured with a second process busy). Passive waiting costs nothing measurable otherwise.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"
