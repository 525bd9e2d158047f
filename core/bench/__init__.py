"""Benchmarks (printed tables + JSON, never timed tests): ``exact_bench`` for the exact tracer."""
