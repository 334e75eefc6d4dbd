"""`python -m waldo_jax` runs the `waldo` command line."""

import sys

from waldo_jax.cli import main

sys.exit(main())
