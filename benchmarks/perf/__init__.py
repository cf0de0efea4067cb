"""The suite's own performance checks, apart from the harness they measure.

Each module runs as ``python -m benchmarks.perf.NAME`` and measures side by side in one run
(a ratio, never a timed assertion): ``throughput`` (steps per second against a C RATTLE
loop), ``scaling`` (cost per step against N, every family, against a C O(N) RATTLE),
``efficiency`` (each family's time per step against a native yardstick of the same
algorithm), ``exudyn`` (``genalpha`` against Exudyn's generalized-alpha, per step, on
the chains; Exudyn is the ``perf`` extra), ``parallel_speedup`` (engines and worker
counts on one suite) and ``suite_time`` (each suite end to end against its budget, and with
``--compile`` what compiling costs, cold and warm). The C yardsticks are in ``yardstick/``;
``processes`` runs them and the other child processes and reads their peak memory.
"""
