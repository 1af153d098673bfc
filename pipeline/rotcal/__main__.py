"""``python -m rotcal``: the rotcal command line."""

from rotcal.cli import main

main()
