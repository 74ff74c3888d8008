"""The project's benchmarks: speed, memory and accuracy measurements behind the numbers in docs/.

Run them from the repository root as a package (no edits of the import path; one module imports another as
``benchmarks.<name>``)::

    python -m benchmarks list                 # each benchmark and what it measures
    python -m benchmarks run NAME [options]   # run one (``--help`` shows its options)

Results go to ``benchmarks/results/`` (JSON or JSON lines, one row per run, with the hardware and commit) and the
tables made from them to docs/.
"""
