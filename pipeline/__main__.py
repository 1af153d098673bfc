"""``python -m pipeline``: the rotcal command line."""

from pipeline.cli import main

main()
