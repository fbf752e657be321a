"""Benchmarks behind ``gf-cli bench``: each returns JSON-able records and prints a table."""
