"""Overnight batch: the SQLite job store, the runner and its executors."""
