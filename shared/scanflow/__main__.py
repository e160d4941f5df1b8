"""`python -m scanflow ...` is the same as the `scanflow` command."""

from scanflow.cli import main

main()
