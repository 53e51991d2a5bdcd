"""`python -m jaxmap ...`: the `jaxmap` command (`jaxmap.cli.main`)."""
import sys

from jaxmap.cli import main

sys.exit(main())
