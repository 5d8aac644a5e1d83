"""``python -m estimator``."""

import sys

from estimator.runtime import console_main

sys.exit(console_main())
