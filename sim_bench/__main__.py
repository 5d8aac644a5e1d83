"""``python -m sim_bench``."""

import sys

from sim_bench.cli import main

sys.exit(main())
