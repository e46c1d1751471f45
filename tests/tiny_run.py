"""The smallest learner a training test needs (every width 16: tiny runs finish in seconds), as the
``[agent]`` table that ends a test's TOML config."""

TINY_AGENT_TOML = """[agent]
feature_dim = 16
encoder_hidden = 16
encoder_global = 16
actor_hidden = 16
critic_hidden = 16
"""
