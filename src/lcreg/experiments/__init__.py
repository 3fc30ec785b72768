"""The experiments beside the library.

The paper's tables (:mod:`.reproduce`, ``lcreg reproduce``) and the benchmark harness (:mod:`.benchmarking`,
:mod:`.evaluation`) that the ``benchmarks/`` scripts front.

The library (everything else under ``lcreg``) never imports this package; this package builds models and data from
the same YAML configs (:mod:`lcreg.config`) as the ``lcreg`` CLI and reads the library's public functions.
"""
