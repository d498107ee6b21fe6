"""Speed benchmarks, one module per component, each a ``main(argv)`` that prints measured figures.

Run through the CLI (``dovesei bench-sim``, ``bench-segmenter``, ``bench-policy``, ``bench-loop``,
``bench-codec``, ``bench-odometry``); none is a test, and nothing in ``services/`` or ``shared/`` imports them.
"""
