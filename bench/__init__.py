"""Benchmarks: run each as ``python -m bench.NAME`` from the repository root (bench/ssl.py would
shadow the standard library's ssl if bench/ itself were on the path)."""
