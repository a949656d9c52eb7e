"""Throughput and time-to-quality benchmarks (``make bench`` = ``python -m benchmarks``)."""
