"""`python -m station` runs the CLI (used where the console script is not on PATH)."""

from station.cli import app

app(prog_name="station")
