"""Lacuna: real-time gap filling for live motion capture."""
__version__ = "0.1.0"
