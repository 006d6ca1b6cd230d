"""`python -m jaxems`: the command line."""

from .cli import run

run()
