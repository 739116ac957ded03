"""Diagnostics: injected providers that benchmarks use, outside the hot path."""
