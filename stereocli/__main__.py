"""``python -m stereocli`` runs the command line."""

from .cli.main import main

main()
