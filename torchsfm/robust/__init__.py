"""Robust estimation: the one batched RANSAC engine, its samplers and model plug-ins."""
