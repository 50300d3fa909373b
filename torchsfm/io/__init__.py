"""Readers and writers of data sets and model files."""
