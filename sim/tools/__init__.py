"""Command-line tools beside runs: benchmarks (``make bench``), the marker lookup tables
and the rendered rocky scene the matcher's tests and benchmark use."""
