"""``python -m scanreg.app``: the ``scanreg`` command."""

from scanreg.app.cli import main

main()
