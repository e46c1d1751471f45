"""hydo learners: encoder, motion policies, critics, the six algorithms, replay, checkpoints.

Tensors in, tensors out: of ``sim`` only the pure-numpy contract modules, nothing of ``robot``.
Start at ``models.algos``; ``models.choices`` (the algorithm table and every named choice) imports no
torch, so the CLI can offer the choices without loading it.
"""
