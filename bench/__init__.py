"""The benchmarks, each a module run from the repository root as ``python -m bench.<name>`` (``python -m bench.run``
runs the suite); :mod:`bench.common` holds what they share, :mod:`bench.settings` the reader of config dataclasses
into command-line options."""
