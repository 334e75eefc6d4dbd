"""`python -m waldo_jax.cli`: the `waldo` command."""

import sys

from waldo_jax.cli import main

sys.exit(main())
