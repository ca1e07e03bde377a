"""jaxskel benchmarks: per-stage and whole-fit timings against a plain numpy/scipy reference.

``python -m bench`` (or ``python bench/run.py``) runs every case in its own
process, prints a table and writes JSON (and optionally a log-log scaling plot).
See :mod:`bench.run` for the options, :mod:`bench.cases` for what is measured,
and :mod:`bench.reference` for the reference implementation.
"""
