"""affinebody: classical and quantum mechanics of affinely-rigid bodies."""
__version__ = "0.1.0"
