"""Splat and mesh writers, the quality gate and the report."""
