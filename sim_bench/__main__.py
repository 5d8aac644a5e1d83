"""``python -m sim_bench``."""

import sys

from sim_bench.entry import console_main

sys.exit(console_main())
