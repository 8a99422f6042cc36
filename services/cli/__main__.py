"""`python -m topseg.services.cli`: the `topseg` command."""

from topseg.services.cli import console

console()
