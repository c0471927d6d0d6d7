"""``python -m benchmarks``: the same command line as the ``recon-bench`` console script."""

import sys

from benchmarks.cli import main

sys.exit(main())
