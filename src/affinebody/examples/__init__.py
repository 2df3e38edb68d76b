"""Built-in example configurations (TOML resources), e.g. ``demo.toml`` for ``affinebody demo``."""
