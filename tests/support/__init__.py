"""References shared by the tests and the benchmarks (``bench/`` imports them from here; product tests
import nothing from ``bench/``): an independent ray caster and image measures (:mod:`.reference`) and
partial captures made from real data (:mod:`.captures`)."""
