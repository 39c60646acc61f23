"""Benchmarks: ``python -m bench`` (``make bench``) runs every module listed in ``bench.__main__``."""
