"""Packaged sample configurations (the built-in simulated cell)."""
