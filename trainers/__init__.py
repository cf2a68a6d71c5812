"""Algorithms, evaluation and command-line entry points."""
