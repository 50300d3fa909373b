"""Readers and writers of data sets and model files."""

from torchsfm.io.bal import read_bal, write_bal

__all__ = ["read_bal", "write_bal"]
