"""`make bench`: dyn_node measured side by side with the peers people would use instead.

Run from the repository root: ``python -m benchmarks.run [--only dynamics,live,...] [--quick]``.
Raw figures go to ``bench_out/bench.json``; ``docs/BENCHMARKS.md`` is generated from them.
"""
