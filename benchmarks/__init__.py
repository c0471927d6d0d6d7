"""Benchmarks of recon and data_synth: the blind diagnosis benchmark, the calibration of its
allowances, and the speed and accuracy measurements behind the documented figures.

This package sits above recon and data_synth and may import anything from them; neither
imports it (tests/pipeline/test_cli.py holds the rule). Each benchmark is a module with a
``main(argv)`` entry point, run as ``recon-bench NAME`` (benchmarks/cli.py lists them) or as
``python -m benchmarks.MODULE``.
"""
