"""Allow ``python -m licalib_cli``."""

from licalib_cli.cli import main

main()
