"""What a benchmark run is: `BenchConfig` read from `benchmarks/<name>.yaml`, a profile and the
command line's overrides, and every field's declared valid values, checked at plan time.
Imports only `harness.common`.
"""
