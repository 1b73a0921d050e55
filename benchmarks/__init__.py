"""`make bench`: thesis-scale speed measurements (``python -m benchmarks.run``)."""
