"""The package's version: the one place it is written (layer 0, imports nothing)."""

__version__ = "0.1.0.dev0"
