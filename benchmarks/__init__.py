"""Benchmarks of seanv-analysis (run with `make bench`)."""
