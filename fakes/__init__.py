"""Simulated hardware behind the same interfaces, and where possible the same wire protocols."""
