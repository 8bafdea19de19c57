"""Tests of the benchmark scripts themselves (``bench/``): the only tests that import ``bench``."""
