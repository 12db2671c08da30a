"""``python -m rasterserver`` runs the command line."""

from rasterserver.cli import run

run()
